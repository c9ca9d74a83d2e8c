"""``GET /metrics``: this worker process's Prometheus text (:class:`occflownet.serve.metrics.Metrics`)."""
from __future__ import annotations

from fastapi import APIRouter
from starlette.responses import Response

from occflownet.serve.dependencies import MetricsDep
from occflownet.serve.metrics import CONTENT_TYPE
from occflownet.serve.schemas import error_doc

router = APIRouter()

RESPONSES = {200: {"description": "Prometheus text exposition (version 0.0.4)",
                   "content": {"text/plain": {"schema": {"type": "string"}}}},
             401: error_doc("API key required")}


@router.get("/metrics", response_class=Response, responses=RESPONSES,
            summary="Prometheus metrics of this worker process")
async def metrics(registry: MetricsDep) -> Response:
    return Response(registry.render(), media_type=CONTENT_TYPE)
