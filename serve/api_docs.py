"""OpenAPI descriptions of the routes: pydantic models for the JSON bodies, content maps for the binary ones."""
from __future__ import annotations

from pydantic import BaseModel, Field

from occflownet.occ3d import CAMERAS


class ErrorBody(BaseModel):
    code: str = Field(description="machine-readable error code, e.g. bad_image, bad_calibration, saturated")
    message: str = Field(description="what was wrong, naming the camera/part/field")


class ErrorResponse(BaseModel):
    error: ErrorBody


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
    model: dict = Field(description="preset and occflownet_version of the model")
    timings_ms: dict[str, float] = Field(description="decode, queue, inference, encode, total (milliseconds)")


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    status: str
    warmup_seconds: float | None


def _error(description: str) -> dict:
    return {"model": ErrorResponse, "description": description}


_SHAPE_HEADERS = {
    "X-Occupancy-Shape": {"description": "grid shape, e.g. 200,200,16", "schema": {"type": "string"}},
    "X-Occupancy-Dtype": {"description": "uint8", "schema": {"type": "string"}},
    "X-Occupancy-Axes": {"description": "x,y,z (ego frame)", "schema": {"type": "string"}},
    "Server-Timing": {"description": "decode, queue, inference, encode durations (ms)", "schema": {"type": "string"}},
}
_BINARY = {"schema": {"type": "string", "format": "binary"}}

OCCUPANCY_RESPONSES = {
    200: {
        "description": "The occupancy grid uint8 [200, 200, 16] ([x, y, z], ego frame; 17 = free) in the format "
                       "chosen by Accept: application/json (default), application/octet-stream (raw C-order bytes),"
                       " application/x-npy (.npy file), image/png (top-down picture: up = +x, left = +y).",
        "model": OccupancyJSON,
        "content": {"application/octet-stream": _BINARY, "application/x-npy": _BINARY, "image/png": _BINARY},
        "headers": _SHAPE_HEADERS,
    },
    400: _error("an image is not a JPEG/PNG, truncated or corrupt (message names the camera), or the calibration "
                "is invalid (wrong shapes, NaN/inf, singular intrinsic, size mismatch), or the multipart body is "
                "malformed"),
    401: _error("API key required (Authorization: Bearer <key>) and missing or wrong"),
    406: _error("Accept names no supported format"),
    413: _error("body over the size limit, or an image header claims more pixels than the limit"),
    415: _error("body is not multipart/form-data"),
    422: _error("missing, extra, repeated or unnamed parts"),
    503: _error("model not ready yet (warming up) or server saturated; see Retry-After"),
}

_PARTS = {cam: {"type": "string", "format": "binary", "description": f"{cam} image, JPEG or PNG (RGB as stored, "
                "EXIF orientation ignored)"} for cam in CAMERAS}
_PARTS["calibration"] = {
    "type": "string",
    "description": 'optional calibration JSON {"cameras": {"CAM_FRONT": {"intrinsic": 3x3, "cam2ego": 4x4}, ...},'
                   ' "image_size": [w, h] (optional)}; without it the model\'s default calibration is used, its '
                   "intrinsics scaled when the images' size differs with the same aspect ratio",
}
OCCUPANCY_REQUEST = {
    "requestBody": {
        "required": True,
        "content": {"multipart/form-data": {
            "schema": {"type": "object", "properties": _PARTS, "required": list(CAMERAS)},
            "encoding": {cam: {"contentType": "image/jpeg, image/png"} for cam in CAMERAS}
            | {"calibration": {"contentType": "application/json"}},
        }},
    }
}

METRICS_RESPONSES = {200: {"description": "Prometheus text exposition (version 0.0.4)",
                           "content": {"text/plain": {"schema": {"type": "string"}}}},
                     401: _error("API key required")}
READY_RESPONSES = {503: _error("warm-up inference not finished (or failed: see message)")}
