"""Probes: ``GET /healthz`` (liveness: the process answers) and ``GET /readyz`` (ready after the warm-up inference).

Both stay open when an API key is configured (:data:`occflownet.serve.middleware.PUBLIC_PATHS`).
"""
from __future__ import annotations

from fastapi import APIRouter

from occflownet.serve.dependencies import RuntimeDep
from occflownet.serve.errors import ApiError
from occflownet.serve.schemas import Health, Ready, error_doc

router = APIRouter()


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers")
async def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Ready, summary="Readiness: model loaded and one warm-up inference done",
            responses={503: error_doc("warm-up inference not finished (or failed: see message)")})
async def readyz(runtime: RuntimeDep) -> Ready:
    if not runtime.ready.is_set():
        raise ApiError(503, "not_ready", runtime.warmup_error or "warm-up inference still running",
                       {"Retry-After": "1"})
    return Ready(status="ready", warmup_seconds=runtime.warmup_seconds)
