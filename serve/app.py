"""The FastAPI app: ``create_app(settings)``; the model is loaded once, at start-up, in the lifespan.

Layout (FastAPI's "bigger applications"): the routes are in :mod:`occflownet.serve.routers` (``/healthz``,
``/readyz``, ``/v1/metadata``, ``/metrics``, ``POST /v1/occupancy``, and the browser page ``/ui`` unless
``settings.ui`` is off; docs/contracts.md, docs/serve.md), what they
need from the process comes through :mod:`occflownet.serve.dependencies`, their JSON bodies are the pydantic models
of :mod:`occflownet.serve.schemas`, and every error answers ``{"error": {"code", "message"}}``
(:mod:`occflownet.serve.errors`). ``/docs`` and ``/redoc`` exist only with ``settings.docs`` (FastAPI's pages,
which load Swagger UI and ReDoc from a CDN); ``/openapi.json`` always. Imports neither torch nor anything that
imports it.

Middlewares, outermost first: the headers of every answer, the one log and 500 of an unhandled exception, the
metrics, the body limits (size, deadline, uploads at once), the API key.
"""
from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager

from fastapi import FastAPI

from occflownet import __version__
from occflownet.serve.dependencies import ServingContext
from occflownet.serve.errors import InternalErrorMiddleware, add_error_handlers
from occflownet.serve.lifecycle import shutdown_signals, watch_parent
from occflownet.serve.limits import BodyLimitsMiddleware, InferenceGate, Uploads
from occflownet.serve.malloc import cap_malloc_arenas
from occflownet.serve.metrics import Metrics
from occflownet.serve.middleware import ApiKeyMiddleware, HeadersMiddleware, MetricsMiddleware
from occflownet.serve.model_runtime import ModelLoadError, ModelRuntime
from occflownet.serve.routers import health, metadata, metrics, occupancy, ui
from occflownet.serve.settings import ServeSettings

log = logging.getLogger("occflownet.serve")


def create_app(settings: ServeSettings | None = None, runtime: ModelRuntime | None = None,
               watch_parent_process: bool = False) -> FastAPI:
    """The app. ``settings`` None reads ``OCCFLOWNET_*`` from the environment (uvicorn ``--factory`` workers);
    ``runtime`` lets a caller pass a model it has already loaded (the CLI with one worker, tests);
    ``watch_parent_process``: shut down when the parent process dies (a worker of ``--workers N``)."""
    settings = (settings or ServeSettings.from_env()).resolved()
    cap_malloc_arenas()
    registry = Metrics()
    uploads = Uploads(settings.max_uploads, settings.body_timeout_s, on_change=registry.set_uploads,
                      on_reject=registry.reject)
    docs = {} if settings.docs else {"docs_url": None, "redoc_url": None}
    app = FastAPI(title="occflownet", version=__version__, **docs,
                  lifespan=_lifespan(settings, runtime, registry, uploads, watch_parent_process),
                  description="Camera-only 3D semantic occupancy (OccFlowNet) from six camera images: "
                              "POST six JPEG/PNG images, get the 200×200×16 Occ3D grid in the ego frame.")
    add_error_handlers(app)
    if settings.api_key:
        app.add_middleware(ApiKeyMiddleware, api_key=settings.api_key)
    app.add_middleware(BodyLimitsMiddleware, max_bytes=settings.max_body_bytes, uploads=uploads)
    app.add_middleware(MetricsMiddleware, metrics=registry)
    app.add_middleware(InternalErrorMiddleware)
    app.add_middleware(HeadersMiddleware)  # added last = outermost: every answer passes through it
    for module in (health, metadata, metrics, occupancy):
        app.include_router(module.router)
    if settings.ui:
        app.include_router(ui.make_router())
    return app


def create_app_from_env() -> FastAPI:
    """uvicorn factory for ``--workers N``: every worker process builds its app from the environment, and shuts
    down if the supervisor that started it dies."""
    return create_app(ServeSettings.from_env(), watch_parent_process=True)


def _lifespan(settings: ServeSettings, runtime: ModelRuntime | None, registry: Metrics, uploads: Uploads,
              watch_parent_process: bool):
    """The app's lifespan: load the model (unless given), put the :class:`ServingContext` in ``app.state.ctx``
    for the dependencies, start the warm-up inference in a thread; while serving, SIGTERM/SIGINT drain the uploads
    (:mod:`occflownet.serve.lifecycle`) and, in a worker, the parent is watched; on shutdown, stop the inference
    executor."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        model = runtime
        if model is None:
            try:
                model = ModelRuntime.load(settings.model_path, settings)
            except ModelLoadError as exc:
                log.error("occflownet serve cannot start: %s", exc)
                raise
        gate = InferenceGate(settings.max_inflight, settings.max_queue, on_change=registry.set_gate)
        ctx = ServingContext(settings, model, gate, registry)
        app.state.ctx = ctx
        if settings.warmup and not model.ready.is_set():
            ctx.warmup_task = asyncio.get_running_loop().run_in_executor(None, _warm_up, model, registry)
        else:
            model.ready.set()
            registry.set_ready()
        log.info("model %s loaded (preset %s, sha256 %s); %d inference slot(s) × %d thread(s), queue %d",
                 model.path, model.metadata.preset, model.sha256[:12], settings.max_inflight,
                 settings.intra_op_threads, settings.max_queue)
        parent_watch = watch_parent() if watch_parent_process else None
        try:
            with shutdown_signals(asyncio.get_running_loop(), uploads.drain):
                yield
        finally:
            if parent_watch is not None:
                parent_watch.set()
            gate.shutdown()
            registry.process_exited()

    return lifespan


def _warm_up(model: ModelRuntime, registry: Metrics) -> None:
    try:
        model.warm_up()
    except Exception:
        log.exception("warm-up inference failed; /readyz stays 503")
        return
    registry.set_ready()
    log.info("warm-up inference done in %.2f s: ready", model.warmup_seconds)
