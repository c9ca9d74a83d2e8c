"""The FastAPI app: ``create_app(settings)``; the model is loaded once, at start-up, in the lifespan.

Routes (docs/contracts.md, docs/serve.md): ``POST /v1/occupancy``, ``GET /healthz`` (liveness), ``GET /readyz`` (ready after
the warm-up inference), ``GET /v1/metadata``, ``GET /metrics`` (Prometheus text). Errors are always
``{"error": {"code", "message"}}``. Imports neither torch nor anything that imports it.

Request pipeline of ``POST /v1/occupancy`` (CPU work never on the event loop):
Accept → 406 | not warmed up → 503 | queue full → 503 + Retry-After | stream multipart parts (422/413/415) |
read image headers, check pixel limits (413) | calibration (400) | wait for a CPU slot | decode the six images in
threads straight into the [6, H, W, 3] tensor, resizing any not at the common size (400) | run ORT on the inference
thread | encode in a thread | release the slot.
"""
from __future__ import annotations

import asyncio
import logging
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse, Response

from occflownet import __version__
from occflownet.serve import api_docs
from occflownet.serve.calibration import CalibrationError, calibration_for_sizes, parse_calibration
from occflownet.serve.decode import ImageError, check_header, common_size, decode_image, intrinsics_for_size
from occflownet.serve.encode import FORMATS, NotAcceptable, encode, negotiate
from occflownet.serve.errors import CODES, ApiError, error_response
from occflownet.serve.form import read_parts
from occflownet.serve.limits import BodySizeLimitMiddleware, InferenceGate, Saturated
from occflownet.serve.malloc import cap_malloc_arenas
from occflownet.serve.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE
from occflownet.serve.metrics import Metrics
from occflownet.serve.middleware import ApiKeyMiddleware, MetricsMiddleware
from occflownet.serve.model_runtime import ModelLoadError, ModelRuntime
from occflownet.serve.settings import MAX_CALIBRATION_BYTES, ServeSettings

log = logging.getLogger("occflownet.serve")


@dataclass
class ServingContext:
    settings: ServeSettings
    runtime: ModelRuntime
    gate: InferenceGate
    metrics: Metrics
    warmup_task: asyncio.Future | None = None


def create_app(settings: ServeSettings | None = None, runtime: ModelRuntime | None = None) -> FastAPI:
    """The app. ``settings`` None reads ``OCCFLOWNET_*`` from the environment (uvicorn ``--factory`` workers);
    ``runtime`` lets a caller pass a model it has already loaded (the CLI with one worker, tests)."""
    settings = (settings or ServeSettings.from_env()).resolved()
    cap_malloc_arenas()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        model = runtime
        if model is None:
            try:
                model = ModelRuntime.load(settings.model_path, settings)
            except ModelLoadError as exc:
                log.error("occflownet serve cannot start: %s", exc)
                raise
        gate = InferenceGate(settings.max_inflight, settings.max_queue, on_change=metrics.set_gate)
        ctx = ServingContext(settings, model, gate, metrics)
        app.state.ctx = ctx
        if settings.warmup and not model.ready.is_set():
            ctx.warmup_task = asyncio.get_running_loop().run_in_executor(None, _warm_up, model, metrics)
        else:
            model.ready.set()
            metrics.ready = 1
        log.info("model %s loaded (preset %s, sha256 %s); %d inference slot(s) × %d thread(s), queue %d",
                 model.path, model.metadata.preset, model.sha256[:12], settings.max_inflight,
                 settings.intra_op_threads, settings.max_queue)
        try:
            yield
        finally:
            gate.shutdown()

    app = FastAPI(title="occflownet", version=__version__, lifespan=lifespan,
                  description="Camera-only 3D semantic occupancy (OccFlowNet) from six camera images: "
                              "POST six JPEG/PNG images, get the 200×200×16 Occ3D grid in the ego frame.")
    _add_error_handlers(app)
    if settings.api_key:
        app.add_middleware(ApiKeyMiddleware, api_key=settings.api_key)
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.add_middleware(MetricsMiddleware, metrics=metrics)  # added last = outermost: sees every answer
    _add_routes(app)
    return app


def create_app_from_env() -> FastAPI:
    """uvicorn factory for ``--workers N``: every worker process builds its app from the environment."""
    return create_app(ServeSettings.from_env())


def _warm_up(model: ModelRuntime, metrics: Metrics) -> None:
    try:
        model.warm_up()
    except Exception:
        log.exception("warm-up inference failed; /readyz stays 503")
        return
    metrics.ready = 1
    log.info("warm-up inference done in %.2f s: ready", model.warmup_seconds)


def _add_error_handlers(app: FastAPI) -> None:
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


def _ctx(request: Request) -> ServingContext:
    return request.app.state.ctx


def _add_routes(app: FastAPI) -> None:
    @app.get("/healthz", response_model=api_docs.Health, summary="Liveness: the process answers")
    async def healthz():
        return {"status": "ok"}

    @app.get("/readyz", response_model=api_docs.Ready, responses=api_docs.READY_RESPONSES,
             summary="Readiness: model loaded and one warm-up inference done")
    async def readyz(request: Request):
        model = _ctx(request).runtime
        if not model.ready.is_set():
            message = model.warmup_error or "warm-up inference still running"
            return error_response(503, "not_ready", message, {"Retry-After": "1"})
        return {"status": "ready", "warmup_seconds": model.warmup_seconds}

    @app.get("/v1/metadata", summary="The model's contract-v1 metadata and the server's limits",
             responses={401: {"model": api_docs.ErrorResponse, "description": "API key required"}})
    async def metadata(request: Request):
        ctx = _ctx(request)
        md, s = ctx.runtime.metadata, ctx.settings
        return JSONResponse({
            "model": {"file": ctx.runtime.path.name, "sha256": ctx.runtime.sha256, "preset": md.preset,
                      "occflownet_version": md.occflownet_version, "onnx_contract": md.onnx_contract},
            "classes": list(md.classes), "free_index": md.free_index, "grid": md.grid, "cameras": list(md.cameras),
            "class_colors": md.class_colors.tolist(), "threshold": md.threshold, "input_size": list(md.input_size),
            "default_calibration": md.default_calibration,
            "limits": {"max_body_bytes": s.max_body_bytes, "max_image_pixels": s.max_image_pixels,
                       "max_inflight": s.max_inflight, "max_queue": s.max_queue},
            "formats": list(FORMATS), "server": {"occflownet_version": __version__},
        })

    @app.get("/metrics", response_class=Response, responses=api_docs.METRICS_RESPONSES,
             summary="Prometheus metrics of this worker process")
    async def metrics(request: Request):
        return Response(_ctx(request).metrics.render(), media_type=METRICS_CONTENT_TYPE)

    @app.post("/v1/occupancy", response_class=Response, responses=api_docs.OCCUPANCY_RESPONSES,
              openapi_extra=api_docs.OCCUPANCY_REQUEST, summary="Occupancy grid from six camera images")
    async def occupancy(request: Request):
        ctx = _ctx(request)
        try:
            media_type = negotiate(request.headers.get("accept"))
        except NotAcceptable as exc:
            raise ApiError(406, "not_acceptable", str(exc)) from None
        if not ctx.runtime.ready.is_set():
            ctx.metrics.reject("not_ready")
            raise ApiError(503, "not_ready", ctx.runtime.warmup_error or "model is warming up",
                           {"Retry-After": "1"})
        try:
            ctx.gate.admit()
        except Saturated as exc:
            ctx.metrics.reject("saturated")
            raise ApiError(503, "saturated", f"all {ctx.gate.capacity} inference/queue slots are taken; retry "
                           f"in {exc.retry_after} s", {"Retry-After": str(exc.retry_after)}) from None
        try:
            return await _occupancy(request, ctx, media_type)
        finally:
            ctx.gate.leave()


async def _occupancy(request: Request, ctx: ServingContext, media_type: str) -> Response:
    md, settings = ctx.runtime.metadata, ctx.settings
    limits = {cam: settings.max_body_bytes for cam in md.cameras} | {"calibration": MAX_CALIBRATION_BYTES}
    parts = await read_parts(request, limits)
    missing = [cam for cam in md.cameras if cam not in parts]
    if missing:
        raise ApiError(422, "missing_part", f"missing image part(s) {', '.join(missing)}; the request needs one "
                       f"part per camera: {', '.join(md.cameras)} (and optionally 'calibration')")
    try:
        # header-only checks and the calibration first: nothing is decoded, and no slot awaited, for a request
        # refused here
        image_headers = [check_header(cam, parts[cam].data, settings.max_image_pixels) for cam in md.cameras]
        sizes = [(h.width, h.height) for h in image_headers]
        calib = parse_calibration(parts["calibration"].data) if "calibration" in parts else None
        K, T = calibration_for_sizes(calib, md, sizes)
    except ImageError as exc:
        raise ApiError(exc.status, "bad_image" if exc.status == 400 else "image_too_large", str(exc)) from None
    except CalibrationError as exc:
        raise ApiError(400, "bad_calibration", str(exc)) from None

    t_queue = time.perf_counter()
    async with ctx.gate.slot() as slot:
        t_decode = time.perf_counter()
        common = ctx.runtime.fixed_image_size or common_size(sizes)
        images = np.empty((len(md.cameras), common[1], common[0], 3), np.uint8)  # [6, H, W, 3] RGB
        try:
            await asyncio.gather(*(run_in_threadpool(decode_image, cam, parts[cam].data, settings.max_image_pixels,
                                                     images[i]) for i, cam in enumerate(md.cameras)))
        except ImageError as exc:
            raise ApiError(exc.status, "bad_image", str(exc)) from None
        del parts
        K = intrinsics_for_size(K, sizes, common)
        t_infer = time.perf_counter()
        occupancy = await ctx.gate.infer(slot, ctx.runtime.infer, images, K, T)
        t_encode = time.perf_counter()
        timings = {"queue": round((t_decode - t_queue) * 1e3, 3), "decode": round((t_infer - t_decode) * 1e3, 3),
                   "inference": round((t_encode - t_infer) * 1e3, 3)}
        body, headers = await run_in_threadpool(encode, media_type, occupancy, md, timings)
        t_end = time.perf_counter()
    for stage, seconds in (("queue", t_decode - t_queue), ("decode", t_infer - t_decode),
                           ("inference", t_encode - t_infer), ("encode", t_end - t_encode)):
        ctx.metrics.observe_stage(stage, seconds)
    timings["encode"] = round((t_end - t_encode) * 1e3, 3)
    headers["Server-Timing"] = ", ".join(f"{k};dur={timings[k]}" for k in ("queue", "decode", "inference", "encode"))
    return Response(body, media_type=media_type, headers=headers)
