"""Streaming multipart/form-data reader for ``POST /v1/occupancy``: exact part names, raw bytes, early refusal.

Parts are collected as raw bytes whether or not the client gave a filename (no text decoding, no temporary files).
A part with an unexpected or repeated name is refused (422) as soon as its headers arrive, before its data is read;
missing parts are reported (422) once the body has ended. Each part has its own byte limit; the whole body is
bounded by :class:`serve.limits.BodySizeLimitMiddleware`.
"""
from __future__ import annotations

from dataclasses import dataclass

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from occflownet.serve.errors import ApiError
from occflownet.serve.limits import BodyTooLarge


@dataclass
class Part:
    name: str
    filename: str | None
    content_type: str | None
    data: bytes


def _check_content_type(value: str | None) -> bytes:
    media, params = parse_options_header(value or "")
    if media != b"multipart/form-data":
        raise ApiError(415, "unsupported_media_type",
                       f"request body must be multipart/form-data, got {value or 'no Content-Type'!r}")
    boundary = params.get(b"boundary")
    if not boundary:
        raise ApiError(400, "bad_request", "multipart/form-data Content-Type has no boundary parameter")
    return boundary


async def read_parts(request, limits: dict[str, int]) -> dict[str, Part]:
    """Read the request's multipart body → {part name: Part}. ``limits`` maps every allowed part name to its byte
    limit. Raises ApiError: 415 (not multipart), 400 (malformed), 413 (over a limit), 422 (names)."""
    boundary = _check_content_type(request.headers.get("content-type"))
    parts: dict[str, Part] = {}
    state = {"headers": {}, "field": b"", "value": b"", "chunks": [], "size": 0, "name": None, "end": False}

    def on_part_begin():
        state.update(headers={}, field=b"", value=b"", chunks=[], size=0, name=None)

    def on_header_field(data, start, end):
        state["field"] += data[start:end]

    def on_header_value(data, start, end):
        state["value"] += data[start:end]

    def on_header_end():
        state["headers"][state["field"].decode("latin-1").lower()] = state["value"].decode("latin-1")
        state["field"], state["value"] = b"", b""

    def on_headers_finished():
        disposition, params = parse_options_header(state["headers"].get("content-disposition", ""))
        name = params.get(b"name", b"").decode("utf-8", "replace")
        if disposition != b"form-data" or not name:
            raise ApiError(422, "unprocessable", "a part has no Content-Disposition: form-data; name=...")
        if name not in limits:
            raise ApiError(422, "unexpected_part",
                           f"unexpected part {name!r}; allowed parts: {', '.join(limits)}")
        if name in parts:
            raise ApiError(422, "duplicate_part", f"part {name!r} appears more than once")
        state["name"] = name

    def on_part_data(data, start, end):
        state["size"] += end - start
        if state["size"] > limits[state["name"]]:
            raise ApiError(413, "payload_too_large",
                           f"part {state['name']!r} is larger than its limit of {limits[state['name']]} bytes")
        state["chunks"].append(data[start:end])

    def on_part_end():
        name = state["name"]
        filename = _param(state["headers"].get("content-disposition", ""), b"filename")
        parts[name] = Part(name, filename, state["headers"].get("content-type"), b"".join(state["chunks"]))

    def on_end():
        state["end"] = True

    parser = MultipartParser(boundary, {
        "on_part_begin": on_part_begin, "on_header_field": on_header_field, "on_header_value": on_header_value,
        "on_header_end": on_header_end, "on_headers_finished": on_headers_finished, "on_part_data": on_part_data,
        "on_part_end": on_part_end, "on_end": on_end})
    try:
        async for chunk in request.stream():
            if chunk:
                parser.write(chunk)
        parser.finalize()
    except BodyTooLarge as exc:
        raise ApiError(413, "payload_too_large", str(exc), headers={"Connection": "close"}) from None
    except ClientDisconnect:
        raise ApiError(400, "bad_request", "client disconnected during the upload") from None
    except FormParserError as exc:
        raise ApiError(400, "bad_request", f"malformed multipart body: {exc}") from None
    if not state["end"]:
        raise ApiError(400, "bad_request", "multipart body ended before its closing boundary (truncated upload?)")
    return parts


def _param(header: str, key: bytes) -> str | None:
    value = parse_options_header(header)[1].get(key)
    return None if value is None else value.decode("utf-8", "replace")
