"""``GET /metrics``: the Prometheus text of the server, all worker processes together
(:class:`occflownet.serve.metrics.Metrics`)."""
from __future__ import annotations

from fastapi import APIRouter
from starlette.responses import Response

from occflownet.serve.dependencies import MetricsDep
from occflownet.serve.metrics import CONTENT_TYPE
from occflownet.serve.schemas import error_doc

router = APIRouter()

RESPONSES = {200: {"description": "Prometheus text exposition",
                   "content": {"text/plain": {"schema": {"type": "string"}}}},
             401: error_doc("API key required")}


@router.get("/metrics", response_class=Response, responses=RESPONSES,
            summary="Prometheus metrics of the server (every worker)")
async def metrics(registry: MetricsDep) -> Response:
    return Response(registry.render(), media_type=CONTENT_TYPE)
