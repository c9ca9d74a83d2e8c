"""The JSON bodies of the API as pydantic models: each is both the OpenAPI schema and what the server sends.

- :class:`ErrorResponse` — the one error shape, ``{"error": {"code", "message"}}`` (built by
  :func:`occflownet.serve.errors.error_response`, the only place that writes it);
- :class:`Health`, :class:`Ready` — ``/healthz``, ``/readyz``;
- :class:`Metadata` — ``/v1/metadata``;
- :class:`OccupancyJSON` — the ``application/json`` answer of ``POST /v1/occupancy`` (written by
  :func:`occflownet.serve.encode.encode_json`; the binary formats are described in :mod:`.routers.occupancy`).
"""
from __future__ import annotations

from pydantic import BaseModel, Field


class ErrorBody(BaseModel):
    code: str = Field(description="machine-readable error code, e.g. bad_image, bad_calibration, saturated")
    message: str = Field(description="what was wrong, naming the camera/part/field")


class ErrorResponse(BaseModel):
    error: ErrorBody


def error_doc(description: str) -> dict:
    """An OpenAPI ``responses`` entry for an error status: the error shape and what the status means."""
    return {"model": ErrorResponse, "description": description}


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    status: str
    warmup_seconds: float | None


class ModelFile(BaseModel):
    file: str = Field(description="file name of the served ONNX model")
    sha256: str = Field(description="SHA-256 of the model file (hex)")
    preset: str | None
    occflownet_version: str | None = Field(description="occflownet version that exported the model")
    onnx_contract: str = Field(description='"v1"')


class Limits(BaseModel):
    max_body_bytes: int
    max_image_pixels: int = Field(description="pixels per image, checked from the header before decoding")
    max_inflight: int = Field(description="requests computing at once in this worker")
    max_queue: int = Field(description="requests admitted beyond those computing; more get 503")
    max_uploads: int = Field(description="request bodies received at once in this worker; more get 503")
    body_timeout_s: float = Field(description="seconds a request body may take to arrive; then 408")


class Server(BaseModel):
    occflownet_version: str


class Metadata(BaseModel):
    """The model's contract-v1 metadata (docs/contracts.md) and this server's limits and formats."""

    model: ModelFile
    classes: list[str] = Field(description="class names; index = class id")
    free_index: int = Field(description="class id of free space")
    grid: dict = Field(description="lower/upper corners [m], voxel_size [m], shape, axes, frame (ego)")
    cameras: list[str] = Field(description="the image part names, in the graph's camera order")
    class_colors: list[list[int]] = Field(description="RGB per class id, as in the image/png answer")
    threshold: float
    input_size: list[int] = Field(description="[H, W] the graph resizes the images to internally")
    default_calibration: dict = Field(description="calibration JSON used when a request has no calibration part")
    limits: Limits
    formats: list[str] = Field(description="media types POST /v1/occupancy can answer, by preference")
    server: Server


class OccupancyModel(BaseModel):
    preset: str | None
    occflownet_version: str | None


class OccupancyJSON(BaseModel):
    shape: list[int] = Field(description="[X, Y, Z] = [200, 200, 16]")
    dtype: str = Field(description="always uint8")
    axes: list[str] = Field(description='["x", "y", "z"]: ego frame, x forward, y left, z up')
    order: str = Field(description="C: z varies fastest in occupancy_base64")
    frame: str
    classes: list[str] = Field(description="class names; index = class id")
    free_index: int = Field(description="class id of free space (17)")
    grid: dict = Field(description="lower/upper corners [m], voxel_size [m], shape, axes, frame")
    occupancy_base64: str = Field(description="base64 of the C-order uint8 bytes (X·Y·Z = 640,000 bytes)")
    class_counts: dict[str, int] = Field(description="number of voxels per class name")
    model: OccupancyModel = Field(description="preset and occflownet_version of the model")
    timings_ms: dict[str, float] = Field(description="queue, decode, inference, encode, total (milliseconds)")
