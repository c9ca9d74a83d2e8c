"""``GET /v1/metadata``: the served model's contract-v1 metadata and this server's limits and formats."""
from __future__ import annotations

from fastapi import APIRouter

from occflownet import __version__
from occflownet.serve.dependencies import RuntimeDep, SettingsDep
from occflownet.serve.encode import FORMATS
from occflownet.serve.schemas import Limits, Metadata, ModelFile, Server, error_doc

router = APIRouter()


@router.get("/v1/metadata", response_model=Metadata, responses={401: error_doc("API key required")},
            summary="The model's contract-v1 metadata and the server's limits")
async def metadata(runtime: RuntimeDep, settings: SettingsDep) -> Metadata:
    md = runtime.metadata
    return Metadata(
        model=ModelFile(file=runtime.path.name, sha256=runtime.sha256, preset=md.preset,
                        occflownet_version=md.occflownet_version, onnx_contract=md.onnx_contract),
        classes=list(md.classes), free_index=md.free_index, grid=md.grid, cameras=list(md.cameras),
        class_colors=md.class_colors.tolist(), threshold=md.threshold, input_size=list(md.input_size),
        default_calibration=md.default_calibration,
        limits=Limits(max_body_bytes=settings.max_body_bytes, max_image_pixels=settings.max_image_pixels,
                      max_inflight=settings.max_inflight, max_queue=settings.max_queue,
                      max_uploads=settings.max_uploads, body_timeout_s=settings.body_timeout_s),
        formats=list(FORMATS), server=Server(occflownet_version=__version__))
