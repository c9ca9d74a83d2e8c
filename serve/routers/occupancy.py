"""``POST /v1/occupancy``: six camera images (multipart) → the Occ3D occupancy grid of the ego frame.

Request pipeline (CPU work never on the event loop), each step refusing what it can before the next:
Accept → 406 | not warmed up → 503 | inference queue already full → 503 + Retry-After (before the body is read) |
stream multipart parts (422/413/415/400; the body limits' 408/413/503) | read image headers, check pixel limits
(413/400) | the frame's calibration for the tensor size (400) | admission to the inference queue (503 +
Retry-After) | wait for a CPU slot | decode the six images in threads straight into the [6, H, W, 3] tensor,
resizing any not at the common size (400) | run ORT on the inference thread | encode in a thread | release the
slot. A request takes a place in the inference queue only once its whole body has been read and checked, so a
client that uploads slowly or stalls holds nothing but its own upload (bounded in time and number,
:mod:`occflownet.serve.limits`). The model's inputs come from the one feeds function (``ModelRuntime.frame`` →
``FrameCalibration.inputs``, :mod:`occflownet.runtime`), as the warm-up's.
"""
from __future__ import annotations

import asyncio
import time

import numpy as np
from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response

from occflownet.contract import MAX_CALIBRATION_BYTES, CalibrationError
from occflownet.occ3d import CAMERAS
from occflownet.runtime import FrameCalibration
from occflownet.serve.decode import ImageError, check_header, decode_image, decode_reduction
from occflownet.serve.dependencies import GateDep, MediaTypeDep, MetricsDep, ReadyRuntimeDep, SettingsDep
from occflownet.serve.encode import encode
from occflownet.serve.errors import ApiError
from occflownet.serve.form import FormPart, Part, openapi_request_body, read_parts
from occflownet.serve.limits import InferenceGate, Saturated
from occflownet.serve.metrics import Metrics
from occflownet.serve.model_runtime import ModelRuntime
from occflownet.serve.schemas import OccupancyJSON, error_doc
from occflownet.serve.settings import DEFAULT_MAX_BODY_BYTES

router = APIRouter()

_SHAPE_HEADERS = {
    "X-Occupancy-Shape": {"description": "grid shape, e.g. 200,200,16", "schema": {"type": "string"}},
    "X-Occupancy-Dtype": {"description": "uint8", "schema": {"type": "string"}},
    "X-Occupancy-Axes": {"description": "x,y,z (ego frame)", "schema": {"type": "string"}},
    "Server-Timing": {"description": "decode, queue, inference, encode durations (ms)", "schema": {"type": "string"}},
}
_BINARY = {"schema": {"type": "string", "format": "binary"}}
RESPONSES = {
    200: {
        "description": "The occupancy grid uint8 [200, 200, 16] ([x, y, z], ego frame; 17 = free) in the format "
                       "chosen by Accept: application/json (default), application/octet-stream (raw C-order bytes),"
                       " application/x-npy (.npy file), image/png (top-down picture: up = +x, left = +y).",
        "model": OccupancyJSON,
        "content": {"application/octet-stream": _BINARY, "application/x-npy": _BINARY, "image/png": _BINARY},
        "headers": _SHAPE_HEADERS,
    },
    400: error_doc("an image is not a JPEG/PNG, truncated or corrupt (message names the camera), or the "
                   "calibration is invalid (wrong shapes, NaN/inf, singular intrinsic, size mismatch), or the "
                   "multipart body is malformed"),
    401: error_doc("API key required (Authorization: Bearer <key>) and missing or wrong"),
    406: error_doc("Accept names no supported format"),
    408: error_doc("the body did not arrive in full within the body timeout of its headers (connection closed)"),
    413: error_doc("body over the size limit, or an image header claims more pixels than the limit"),
    415: error_doc("body is not multipart/form-data"),
    422: error_doc("missing, extra, repeated or unnamed parts"),
    503: error_doc("model not ready yet (warming up), server saturated or too many uploads at once (see "
                   "Retry-After), or shutting down"),
}


def occupancy_parts(cameras: tuple[str, ...], max_image_bytes: int) -> dict[str, FormPart]:
    """The parts ``POST /v1/occupancy`` allows: one image per camera (required, at most ``max_image_bytes``) and the
    optional calibration JSON (at most MAX_CALIBRATION_BYTES, a file or a plain field). The reader's names and
    limits and the OpenAPI request body both come from here."""
    images = {cam: FormPart(max_image_bytes, True, f"{cam} image, JPEG or PNG (RGB as stored, EXIF orientation "
                            "ignored)", content_type="image/jpeg, image/png") for cam in cameras}
    calibration = FormPart(
        MAX_CALIBRATION_BYTES, False, 'optional calibration JSON {"cameras": {"CAM_FRONT": {"intrinsic": 3x3, '
        '"cam2ego": 4x4}, ...}, "image_size": [w, h] (optional)}; without it the model\'s default calibration is '
        "used, its intrinsics scaled when the images' size differs with the same aspect ratio",
        binary=False, content_type="application/json")
    return images | {"calibration": calibration}


REQUEST = {"requestBody": openapi_request_body(occupancy_parts(CAMERAS, DEFAULT_MAX_BODY_BYTES))}


@router.post("/v1/occupancy", response_class=Response, responses=RESPONSES, openapi_extra=REQUEST,
             summary="Occupancy grid from six camera images")
async def occupancy(request: Request, media_type: MediaTypeDep, runtime: ReadyRuntimeDep, settings: SettingsDep,
                    gate: GateDep, metrics: MetricsDep) -> Response:
    """Six camera images (one multipart part per camera, JPEG or PNG, and optionally a calibration part) → the
    occupancy grid uint8 [200, 200, 16] ([x, y, z] of the ego frame, 17 = free) in the format chosen by Accept."""
    _admit(gate, metrics, gate.check)                      # full already: refused before the upload
    parts = await read_parts(request, occupancy_parts(runtime.metadata.cameras, settings.max_body_bytes))
    reductions, frame = _checked_inputs(parts, runtime, settings.max_image_pixels)
    _admit(gate, metrics, gate.admit)
    try:
        body, headers = await _compute(gate, runtime, metrics, parts, reductions, frame, settings.max_image_pixels,
                                       media_type)
        return Response(body, media_type=media_type, headers=headers)
    finally:
        gate.leave()


def _admit(gate: InferenceGate, metrics: Metrics, step) -> None:
    """``gate.check`` or ``gate.admit``; Saturated → 503 ``saturated`` with Retry-After (counted)."""
    try:
        step()
    except Saturated as exc:
        metrics.reject("saturated")
        raise ApiError(503, "saturated", f"all {gate.capacity} inference/queue slots are taken; retry in "
                       f"{exc.retry_after} s", {"Retry-After": str(exc.retry_after)}) from None


def _checked_inputs(parts: dict[str, Part], runtime: ModelRuntime, max_pixels: int
                   ) -> tuple[list[int], FrameCalibration]:
    """Everything checkable before a slot is awaited, nothing decoded: all parts present, each image's header
    (JPEG/PNG, complete, ≤ ``max_pixels``), the calibration → (the scale 1/n each image is decoded at (JPEGs at
    reduced scale, docs/contracts.md), the frame's calibration: the tensor size (w, h), intrinsics float32
    [6, 3, 3] for it, cam2ego float32 [6, 4, 4] camera → ego). Raises ApiError (422, 413, 400)."""
    md = runtime.metadata
    missing = [cam for cam in md.cameras if cam not in parts]
    if missing:
        raise ApiError(422, "missing_part", f"missing image part(s) {', '.join(missing)}; the request needs one "
                       f"part per camera: {', '.join(md.cameras)} (and optionally 'calibration')")
    try:
        headers = [check_header(cam, parts[cam].data, max_pixels) for cam in md.cameras]
        reductions = [decode_reduction(h, md.input_size) for h in headers]
        calib = parts["calibration"].data if "calibration" in parts else None
        frame = runtime.frame(calib, [(h.width, h.height) for h in headers], reductions)
    except ImageError as exc:
        raise ApiError(exc.status, "bad_image" if exc.status == 400 else "image_too_large", str(exc)) from None
    except CalibrationError as exc:
        raise ApiError(400, "bad_calibration", str(exc)) from None
    return reductions, frame


async def _compute(gate: InferenceGate, runtime: ModelRuntime, metrics: Metrics, parts: dict[str, Part],
                  reductions: list[int], frame: FrameCalibration, max_pixels: int, media_type: str
                  ) -> tuple[bytes, dict[str, str]]:
    """In one CPU slot: decode the images (in threads, each at 1/``reductions[i]``) into uint8 [6, h, w, 3] RGB at
    ``frame.size`` (the common size or the graph's fixed size, see :meth:`ModelRuntime.frame`), inference on
    ``frame.inputs(images)`` (intrinsics already for that size, cam2ego) → occupancy uint8 [200, 200, 16], encoded
    as ``media_type`` → (body, headers with Server-Timing). ``parts`` is emptied once decoded (the uploads are not
    kept during inference)."""
    cameras = runtime.metadata.cameras
    t_queue = time.perf_counter()
    async with gate.slot() as slot:
        t_decode = time.perf_counter()
        images = np.empty(frame.image_shape, np.uint8)
        try:
            await asyncio.gather(*(run_in_threadpool(decode_image, cam, parts[cam].data, max_pixels, images[i],
                                                     reductions[i])
                                   for i, cam in enumerate(cameras)))
        except ImageError as exc:
            raise ApiError(exc.status, "bad_image", str(exc)) from None
        parts.clear()
        inputs = frame.inputs(images)
        t_infer = time.perf_counter()
        occupancy = await gate.infer(slot, runtime.infer, inputs)
        t_encode = time.perf_counter()
        timings = {"queue": round((t_decode - t_queue) * 1e3, 3), "decode": round((t_infer - t_decode) * 1e3, 3),
                   "inference": round((t_encode - t_infer) * 1e3, 3)}
        body, headers = await run_in_threadpool(encode, media_type, occupancy, runtime.metadata, timings)
        t_end = time.perf_counter()
    for stage, seconds in (("queue", t_decode - t_queue), ("decode", t_infer - t_decode),
                           ("inference", t_encode - t_infer), ("encode", t_end - t_encode)):
        metrics.observe_stage(stage, seconds)
    timings["encode"] = round((t_end - t_encode) * 1e3, 3)
    headers["Server-Timing"] = ", ".join(f"{k};dur={timings[k]}" for k in ("queue", "decode", "inference", "encode"))
    return body, headers
