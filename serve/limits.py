"""Limits that protect the server: the request body size (ASGI middleware) and the inference concurrency gate.

Body size: a request whose ``Content-Length`` exceeds the limit is answered 413 at once, before any of its body is
read (a client that sent ``Expect: 100-continue`` never uploads it); a body without a length (chunked) is counted
as it streams and the request fails with 413 as soon as the count passes the limit. Nothing is buffered here.

Inference gate: at most ``max_inflight`` requests do CPU work (decode, inference on a dedicated thread, encode) at
once, all of it off the event loop; at most ``max_queue`` more requests are admitted and wait (reading their body,
waiting for a slot). Beyond that a request is refused at once with 503 and a ``Retry-After`` estimated from the
recent inference time and the queue length.
"""
from __future__ import annotations

import asyncio
import math
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager

from occflownet.serve.errors import error_response


class BodyTooLarge(Exception):
    """The request body passed the configured limit while streaming."""

    def __init__(self, limit: int):
        super().__init__(f"request body is larger than the limit of {limit} bytes")
        self.limit = limit


def too_large_response(limit: int, detail: str = ""):
    message = f"request body is larger than the limit of {limit} bytes{detail}"
    return error_response(413, "payload_too_large", message, headers={"Connection": "close"})


class BodySizeLimitMiddleware:
    """Pure ASGI middleware: 413 on a declared or streamed body over ``max_bytes`` (see module docstring)."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        for key, value in scope["headers"]:
            if key == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.max_bytes:
                    response = too_large_response(self.max_bytes, f" (Content-Length: {declared})")
                    return await response(scope, receive, send)
        received = 0
        started = False

        async def limited_receive():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
            return message

        async def tracking_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge:
            if started:
                raise
            await too_large_response(self.max_bytes)(scope, receive, send)


class Saturated(Exception):
    """No room in the inference queue; ``retry_after`` is the suggested wait in whole seconds."""

    def __init__(self, retry_after: int):
        super().__init__("server saturated")
        self.retry_after = retry_after


class _Slot:
    """One held CPU slot; ``pending`` is the inference future still running on its thread, if any."""

    def __init__(self):
        self.pending: asyncio.Future | None = None


class InferenceGate:
    """Admission (bounded queue) and a bounded number of requests doing CPU work at once.

    A slot covers all of a request's CPU-heavy work (decoding its six images, the inference on a dedicated thread,
    encoding the answer): with ``max_inflight`` = cores // intra-op threads, one request per core group computes
    at a time, so decode threads never compete with onnxruntime's threads (oversubscription cost 35 % throughput
    in docs/serve.md's measurements). Use from the event loop only::

        gate.admit()                      # raises Saturated when running + waiting would pass the capacity
        try:
            async with gate.slot() as slot:
                ...decode in threads...
                result = await gate.infer(slot, fn, *args)
        finally:
            gate.leave()
    """

    def __init__(self, max_inflight: int, max_queue: int, on_change=None):
        self.max_inflight = max_inflight
        self.capacity = max_inflight + max_queue
        self.admitted = 0
        self.running = 0
        self._slots = asyncio.Semaphore(max_inflight)
        self._executor = ThreadPoolExecutor(max_inflight, thread_name_prefix="occflownet-infer")
        self._mean_s: float | None = None
        self._on_change = on_change or (lambda queued, running: None)

    def _changed(self) -> None:
        self._on_change(self.admitted - self.running, self.running)

    def retry_after(self) -> int:
        """Seconds until a slot is likely free: mean slot time × (waiting + 1) / slots, in [1, 60]."""
        if self._mean_s is None:
            return 1
        waiting = max(0, self.admitted - self.running) + 1
        return int(min(60, max(1, math.ceil(self._mean_s * waiting / self.max_inflight))))

    def admit(self) -> None:
        if self.admitted >= self.capacity:
            raise Saturated(self.retry_after())
        self.admitted += 1
        self._changed()

    def leave(self) -> None:
        self.admitted -= 1
        self._changed()

    @asynccontextmanager
    async def slot(self):
        """Hold one CPU slot. If the holder is cancelled while its inference thread still runs, the slot is
        released only when that thread finishes, so no more than ``max_inflight`` inferences ever run at once."""
        await self._slots.acquire()
        t0 = time.perf_counter()
        self.running += 1
        self._changed()
        held = _Slot()
        try:
            yield held
        finally:
            seconds = time.perf_counter() - t0
            self._mean_s = seconds if self._mean_s is None else 0.8 * self._mean_s + 0.2 * seconds
            if held.pending is not None and not held.pending.done():
                held.pending.add_done_callback(self._release)
            else:
                self._release(None)

    async def infer(self, held: _Slot, fn, *args):
        """Run ``fn(*args)`` on an inference thread, inside a held slot."""
        held.pending = asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)
        return await asyncio.shield(held.pending)

    def _release(self, _future) -> None:
        self.running -= 1
        self._slots.release()
        self._changed()

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
