"""The four response formats of ``POST /v1/occupancy`` and the ``Accept`` negotiation that picks one.

All formats carry the same grid: occupancy uint8 [X, Y, Z] = [200, 200, 16], axes [x, y, z] of the ego frame
(x forward, y left, z up), C order, class ids 0..16 and ``free_index`` (17) for free space.

- ``application/json`` (default): shape, dtype, axes, order, classes, free index, grid geometry, the grid as
  base64 of the C-order bytes, per-class voxel counts, timings;
- ``application/octet-stream``: the raw X·Y·Z bytes; shape/dtype/axes in ``X-Occupancy-*`` headers;
- ``application/x-npy``: a NumPy ``.npy`` file (``np.load(io.BytesIO(body))``);
- ``image/png``: a top-down picture: each (x, y) column coloured by ``class_colors`` of its highest non-free voxel,
  free columns in the free colour; image up = +x (forward), image left = +y (left), ego at the centre
  (black dot), ``PNG_SCALE`` pixels per voxel.
"""
from __future__ import annotations

import base64
import io
import time

import numpy as np

from occflownet import pictures
from occflownet.serve.schemas import OccupancyJSON, OccupancyModel

JSON = "application/json"
OCTET = "application/octet-stream"
NPY = "application/x-npy"
PNG = "image/png"
FORMATS = (JSON, OCTET, NPY, PNG)  # order = preference among equal q-values
PNG_SCALE = 2


class NotAcceptable(ValueError):
    """No supported media type satisfies the request's Accept header (HTTP 406)."""


def negotiate(accept: str | None) -> str:
    """The media type to answer for an ``Accept`` header (RFC 9110 q-values and wildcards); JSON when absent."""
    if accept is None or not accept.strip():
        return JSON
    best, best_rank = None, None
    for item in accept.split(","):
        pieces = [p.strip() for p in item.split(";")]
        media = pieces[0].lower()
        if not media:
            continue
        q = 1.0
        for param in pieces[1:]:
            key, _, value = param.partition("=")
            if key.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        if q <= 0:
            continue
        for rank, fmt in enumerate(FORMATS):
            kind, sub = fmt.split("/")
            if media in (fmt, "*/*", f"{kind}/*"):
                # exact matches beat wildcards at equal q (specificity), then our preference order
                key = (q, media == fmt, -rank)
                if best is None or key > best_rank:
                    best, best_rank = fmt, key
    if best is None:
        raise NotAcceptable(f"cannot produce any of {accept!r}; supported: {', '.join(FORMATS)}")
    return best


def class_counts(occupancy: np.ndarray, classes: tuple[str, ...]) -> dict[str, int]:
    """Voxels per class name (every class listed, zeros included)."""
    counts = np.bincount(occupancy.ravel(), minlength=len(classes))
    return {name: int(c) for name, c in zip(classes, counts[:len(classes)])}


def shape_headers(occupancy: np.ndarray) -> dict[str, str]:
    return {"X-Occupancy-Shape": ",".join(str(s) for s in occupancy.shape), "X-Occupancy-Dtype": "uint8",
            "X-Occupancy-Axes": "x,y,z"}


def encode_json(occupancy: np.ndarray, metadata, timings_ms: dict) -> bytes:
    """JSON body (:class:`~occflownet.serve.schemas.OccupancyJSON`) of occupancy uint8 [X, Y, Z]; ``timings_ms``
    gets "encode" (time up to the final serialisation) and "total" added."""
    t0 = time.perf_counter()
    occupancy_base64 = base64.b64encode(np.ascontiguousarray(occupancy).tobytes()).decode("ascii")
    counts = class_counts(occupancy, metadata.classes)
    timings_ms["encode"] = round((time.perf_counter() - t0) * 1e3, 3)
    timings_ms["total"] = round(sum(v for k, v in timings_ms.items() if k != "total"), 3)
    body = OccupancyJSON(
        shape=list(occupancy.shape), dtype="uint8", axes=["x", "y", "z"], order="C",
        frame="ego (x forward, y left, z up)", classes=list(metadata.classes), free_index=metadata.free_index,
        grid=metadata.grid, occupancy_base64=occupancy_base64, class_counts=counts,
        model=OccupancyModel(preset=metadata.preset, occflownet_version=metadata.occflownet_version),
        timings_ms=timings_ms)
    return body.model_dump_json().encode("utf-8")


def encode_npy(occupancy: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(occupancy), allow_pickle=False)
    return buf.getvalue()


def encode_png(occupancy: np.ndarray, metadata) -> bytes:
    """The ``image/png`` body: :func:`occflownet.pictures.top_down` in the model's own class colours."""
    return pictures.encode_png(pictures.top_down(occupancy, metadata.class_colors, metadata.free_index,
                                                 scale=PNG_SCALE))


def encode(media_type: str, occupancy: np.ndarray, metadata, timings_ms: dict) -> tuple[bytes, dict[str, str]]:
    """Body and extra headers for one of ``FORMATS``."""
    if media_type == JSON:
        return encode_json(occupancy, metadata, timings_ms), {}
    if media_type == OCTET:
        return np.ascontiguousarray(occupancy).tobytes(), shape_headers(occupancy)
    if media_type == NPY:
        return encode_npy(occupancy), shape_headers(occupancy)
    if media_type == PNG:
        return encode_png(occupancy, metadata), shape_headers(occupancy)
    raise NotAcceptable(media_type)
