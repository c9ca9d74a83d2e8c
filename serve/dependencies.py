"""FastAPI dependencies: what a route needs from the serving context, declared with ``Depends``.

The app's lifespan builds one :class:`ServingContext` per process (settings, model runtime, inference gate, metrics)
and keeps it in ``app.state.ctx``; routes never fetch it by hand but declare what they need:

- ``SettingsDep``, ``RuntimeDep``, ``GateDep``, ``MetricsDep``: the pieces of the context;
- ``ReadyRuntimeDep``: the runtime once its warm-up inference is done, else 503 ``not_ready`` + ``Retry-After: 1``
  (counted in ``occflownet_rejected_total``);
- ``MediaTypeDep``: the answer's media type negotiated from ``Accept``, else 406 ``not_acceptable``.

All are ``async def``: trivial work, so FastAPI runs them on the event loop instead of a thread.
"""
from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request

from occflownet.serve.encode import NotAcceptable, negotiate
from occflownet.serve.errors import ApiError
from occflownet.serve.limits import InferenceGate
from occflownet.serve.metrics import Metrics
from occflownet.serve.model_runtime import ModelRuntime
from occflownet.serve.settings import ServeSettings


@dataclass
class ServingContext:
    """One process's serving state; ``warmup_task`` keeps the warm-up inference's future referenced."""

    settings: ServeSettings
    runtime: ModelRuntime
    gate: InferenceGate
    metrics: Metrics
    warmup_task: asyncio.Future | None = None


async def get_context(request: Request) -> ServingContext:
    return request.app.state.ctx


ContextDep = Annotated[ServingContext, Depends(get_context)]


async def get_settings(ctx: ContextDep) -> ServeSettings:
    return ctx.settings


async def get_runtime(ctx: ContextDep) -> ModelRuntime:
    return ctx.runtime


async def get_gate(ctx: ContextDep) -> InferenceGate:
    return ctx.gate


async def get_metrics(ctx: ContextDep) -> Metrics:
    return ctx.metrics


SettingsDep = Annotated[ServeSettings, Depends(get_settings)]
RuntimeDep = Annotated[ModelRuntime, Depends(get_runtime)]
GateDep = Annotated[InferenceGate, Depends(get_gate)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


async def ready_runtime(runtime: RuntimeDep, metrics: MetricsDep) -> ModelRuntime:
    """The runtime, or 503 ``not_ready`` while the warm-up inference runs (or after it failed: its error)."""
    if not runtime.ready.is_set():
        metrics.reject("not_ready")
        raise ApiError(503, "not_ready", runtime.warmup_error or "model is warming up", {"Retry-After": "1"})
    return runtime


async def accepted_media_type(request: Request) -> str:
    """One of :data:`occflownet.serve.encode.FORMATS` for the request's ``Accept``, or 406 ``not_acceptable``."""
    try:
        return negotiate(request.headers.get("accept"))
    except NotAcceptable as exc:
        raise ApiError(406, "not_acceptable", str(exc)) from None


ReadyRuntimeDep = Annotated[ModelRuntime, Depends(ready_runtime)]
MediaTypeDep = Annotated[str, Depends(accepted_media_type)]
