"""Streaming multipart/form-data reader for ``POST /v1/occupancy``: exact part names, raw bytes, early refusal.

Parts are collected as raw bytes whether or not the client gave a filename (no text decoding, no temporary files).
A part with an unexpected or repeated name is refused (422) as soon as its headers arrive, before its data is read;
missing parts are reported (422) once the body has ended. Each part has its own byte limit; the whole body's size,
its deadline and the number of bodies read at once are :class:`occflownet.serve.limits.BodyLimitsMiddleware`'s
(its refusals, raised from the body reads, pass through here unchanged).

The parts a route allows are one definition, a {name: :class:`FormPart`} dict: the reader's names and limits
(:func:`read_parts`) and the route's OpenAPI request body (:func:`openapi_request_body`) both come from it. FastAPI's
own ``UploadFile``/``File`` handling cannot hold these limits (docs/serve.md, "Why the route reads its own form").
"""
from __future__ import annotations

from dataclasses import dataclass

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from occflownet.serve.errors import ApiError


@dataclass(frozen=True)
class FormPart:
    """One allowed part: its byte ``limit``, whether it is ``required``, its OpenAPI ``description``, whether it is
    ``binary`` (a file) or text, and the media types it is sent as (``content_type``, for the OpenAPI encoding)."""

    limit: int
    required: bool
    description: str
    binary: bool = True
    content_type: str = "application/octet-stream"


def openapi_request_body(parts: dict[str, FormPart]) -> dict:
    """The OpenAPI ``requestBody`` of a multipart/form-data route that allows ``parts``."""
    properties = {name: {"type": "string", **({"format": "binary"} if p.binary else {}),
                         "description": p.description} for name, p in parts.items()}
    return {"required": True, "content": {"multipart/form-data": {
        "schema": {"type": "object", "properties": properties,
                   "required": [name for name, p in parts.items() if p.required]},
        "encoding": {name: {"contentType": p.content_type} for name, p in parts.items()},
    }}}


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


class _PartCollector:
    """The streaming parser's callbacks: each part's headers checked as soon as they end (name, duplicates), its
    data counted against its limit while it streams, the finished parts in :attr:`parts` by name."""

    def __init__(self, parts: dict[str, FormPart]):
        self.limits = {name: p.limit for name, p in parts.items()}
        self.parts: dict[str, Part] = {}
        self.ended = False
        self._begin()

    def callbacks(self) -> dict:
        return {"on_part_begin": self._begin, "on_header_field": self._header_field,
                "on_header_value": self._header_value, "on_header_end": self._header_end,
                "on_headers_finished": self._headers_finished, "on_part_data": self._data,
                "on_part_end": self._part_end, "on_end": self._end}

    def _begin(self) -> None:
        self.headers: dict[str, str] = {}
        self.field, self.value, self.chunks, self.size, self.name = b"", b"", [], 0, None

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self.field += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self.value += data[start:end]

    def _header_end(self) -> None:
        self.headers[self.field.decode("latin-1").lower()] = self.value.decode("latin-1")
        self.field, self.value = b"", b""

    def _headers_finished(self) -> None:
        disposition, params = parse_options_header(self.headers.get("content-disposition", ""))
        name = params.get(b"name", b"").decode("utf-8", "replace")
        if disposition != b"form-data" or not name:
            raise ApiError(422, "unprocessable", "a part has no Content-Disposition: form-data; name=...")
        if name not in self.limits:
            raise ApiError(422, "unexpected_part",
                           f"unexpected part {name!r}; allowed parts: {', '.join(self.limits)}")
        if name in self.parts:
            raise ApiError(422, "duplicate_part", f"part {name!r} appears more than once")
        self.name = name

    def _data(self, data: bytes, start: int, end: int) -> None:
        self.size += end - start
        if self.size > self.limits[self.name]:
            raise ApiError(413, "payload_too_large",
                           f"part {self.name!r} is larger than its limit of {self.limits[self.name]} bytes")
        self.chunks.append(data[start:end])

    def _part_end(self) -> None:
        filename = _param(self.headers.get("content-disposition", ""), b"filename")
        self.parts[self.name] = Part(self.name, filename, self.headers.get("content-type"), b"".join(self.chunks))

    def _end(self) -> None:
        self.ended = True


async def read_parts(request, parts: dict[str, FormPart]) -> dict[str, Part]:
    """Read the request's multipart body → {part name: Part} of the allowed ``parts`` (each with its byte limit).
    Raises ApiError: 415 (not multipart), 400 (malformed), 413 (over a limit), 422 (names), and the body limits'
    own (408, 413, 503: :class:`occflownet.serve.limits.BodyRefused`)."""
    boundary = _check_content_type(request.headers.get("content-type"))
    collector = _PartCollector(parts)
    parser = MultipartParser(boundary, collector.callbacks())
    try:
        async for chunk in request.stream():
            if chunk:
                parser.write(chunk)
        parser.finalize()
    except ClientDisconnect:
        raise ApiError(400, "bad_request", "client disconnected during the upload") from None
    except FormParserError as exc:
        raise ApiError(400, "bad_request", f"malformed multipart body: {exc}") from None
    if not collector.ended:
        raise ApiError(400, "bad_request", "multipart body ended before its closing boundary (truncated upload?)")
    return collector.parts


def _param(header: str, key: bytes) -> str | None:
    value = parse_options_header(header)[1].get(key)
    return None if value is None else value.decode("utf-8", "replace")
