"""Limits that protect the server: what a request body may cost (ASGI middleware) and the inference gate.

Request bodies (:class:`BodyLimitsMiddleware` with one :class:`Uploads` per process):

- size: a ``Content-Length`` over the limit is answered 413 at once, before any of the body is read (a client that
  sent ``Expect: 100-continue`` never uploads it); a body without a length (chunked) is counted as it streams and
  the request fails with 413 as soon as the count passes the limit. Nothing is buffered here.
- time: the whole body must arrive within ``body_timeout_s`` of the request's headers, else 408 ``body_timeout``.
  The deadline covers the body only; once it has ended, reads (a wait for the client's disconnect) are not timed.
- count: at most ``max_uploads`` bodies are received at once (an upload starts when the app first reads the body
  and ends with its last byte); one more is refused with 503 ``busy`` before any of its body is read.
- shutdown: :meth:`Uploads.drain` (SIGTERM, SIGINT) refuses new uploads with 503 ``shutting_down`` and ends those
  still incomplete :data:`DRAIN_GRACE_S` later the same way, so a stalled client cannot hold the shutdown.
Every such refusal carries ``Connection: close``: the connection is not reused after a body that was not read.

Inference gate (:class:`InferenceGate`): a request enters it only once its whole body has been read and checked,
so clients that upload slowly or stall never take a place in it. At most ``max_inflight`` admitted requests do CPU
work (decode, inference on a dedicated thread, encode) at once, all of it off the event loop; at most ``max_queue``
more wait for a slot. Beyond that a request is refused with 503 and a ``Retry-After`` estimated from the recent
time per request and the number waiting: before its body is read when the gate is already full on arrival
(:meth:`InferenceGate.check`), or after it when the gate filled during the upload (:meth:`InferenceGate.admit`).
"""
from __future__ import annotations

import asyncio
import math
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager

from occflownet.serve.errors import ApiError, error_response

DRAIN_GRACE_S = 1.0   # after SIGTERM, how long uploads still arriving get before they are refused
CLOSE = {"Connection": "close"}


class BodyRefused(ApiError):
    """A request body the server will not read further; answered with ``Connection: close``."""


class BodyTooLarge(BodyRefused):
    def __init__(self, limit: int, detail: str = ""):
        super().__init__(413, "payload_too_large", f"request body is larger than the limit of {limit} bytes{detail}",
                         dict(CLOSE))
        self.limit = limit


class BodyTimeout(BodyRefused):
    def __init__(self, seconds: float):
        super().__init__(408, "body_timeout", f"the request body did not arrive in full within {seconds:g} s of "
                         "its headers", dict(CLOSE))


class TooManyUploads(BodyRefused):
    def __init__(self, limit: int):
        super().__init__(503, "busy", f"{limit} request bodies are being received already; retry in 1 s",
                         {"Retry-After": "1", **CLOSE})


class ShuttingDown(BodyRefused):
    def __init__(self):
        super().__init__(503, "shutting_down", "the server is shutting down; send the request again (to another "
                         "instance)", dict(CLOSE))


class Uploads:
    """The request bodies being received in one process: their number (at most ``max_uploads``), their deadline
    (``timeout_s`` after the headers) and the drain at shutdown. Use from the event loop only (``drain`` from a
    signal handler through ``loop.call_soon_threadsafe``). ``on_change(active)`` and ``on_reject(reason)`` report
    to the metrics."""

    def __init__(self, max_uploads: int, timeout_s: float, on_change=None, on_reject=None):
        self.max_uploads = max_uploads
        self.timeout_s = timeout_s
        self.active = 0
        self.draining = False
        self._aborted = False
        self._waiting: set[asyncio.Future] = set()
        self._on_change = on_change or (lambda active: None)
        self._on_reject = on_reject or (lambda reason: None)

    def enter(self) -> None:
        """Start one upload, or raise ShuttingDown (draining) / TooManyUploads (``max_uploads`` in progress)."""
        if self.draining:
            raise ShuttingDown()
        if self.active >= self.max_uploads:
            self._on_reject("uploads")
            raise TooManyUploads(self.max_uploads)
        self.active += 1
        self._on_change(self.active)

    def leave(self) -> None:
        self.active -= 1
        self._on_change(self.active)

    async def receive(self, receive, deadline: float):
        """``await receive()`` unless the loop time ``deadline`` passes first (BodyTimeout) or the drain ends the
        uploads (ShuttingDown)."""
        if self._aborted:
            raise ShuttingDown()
        loop = asyncio.get_running_loop()
        abort = loop.create_future()
        self._waiting.add(abort)
        message = asyncio.ensure_future(receive())
        try:
            done, _ = await asyncio.wait((message, abort), timeout=max(0.0, deadline - loop.time()),
                                         return_when=asyncio.FIRST_COMPLETED)
        finally:
            self._waiting.discard(abort)
            if not message.done():
                message.cancel()
        if message in done:
            return message.result()
        if abort in done:
            raise ShuttingDown()
        raise BodyTimeout(self.timeout_s)

    def drain(self, grace: float = DRAIN_GRACE_S) -> None:
        """Shutdown has begun: refuse new uploads now, end the incomplete ones after ``grace`` seconds."""
        if not self.draining:
            self.draining = True
            asyncio.get_running_loop().call_later(grace, self._abort_all)

    def _abort_all(self) -> None:
        self._aborted = True
        for abort in self._waiting:
            if not abort.done():
                abort.set_result(None)


def _declared_length(scope) -> int | None:
    """The request's Content-Length (-1 when not a number), or None without one."""
    for key, value in scope["headers"]:
        if key == b"content-length":
            try:
                return int(value)
            except ValueError:
                return -1
    return None


def _has_body(scope, declared: int | None) -> bool:
    return (declared is not None and declared != 0) or any(k == b"transfer-encoding" for k, _ in scope["headers"])


class BodyLimitsMiddleware:
    """Pure ASGI middleware: the size, deadline and count of request bodies (see the module docstring)."""

    def __init__(self, app, max_bytes: int, uploads: Uploads):
        self.app = app
        self.max_bytes = max_bytes
        self.uploads = uploads

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = _declared_length(scope)
        if declared is not None and declared > self.max_bytes:
            refusal = BodyTooLarge(self.max_bytes, f" (Content-Length: {declared})")
            return await error_response(refusal.status, refusal.code, refusal.message, refusal.headers)(
                scope, receive, send)
        if not _has_body(scope, declared):
            return await self.app(scope, receive, send)
        await self._limited(scope, receive, send)

    async def _limited(self, scope, receive, send):
        """Run the app with a ``receive`` that enforces the limits; a refusal raised outside the app's own error
        handling is answered here (if nothing was sent yet)."""
        deadline = asyncio.get_running_loop().time() + self.uploads.timeout_s
        state = {"received": 0, "uploading": False, "ended": False, "started": False}

        async def limited_receive():
            if state["ended"]:
                return await receive()
            if not state["uploading"]:
                self.uploads.enter()
                state["uploading"] = True
            message = await self.uploads.receive(receive, deadline)
            if message["type"] == "http.request":
                state["received"] += len(message.get("body", b""))
                if state["received"] > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
            if message["type"] != "http.request" or not message.get("more_body", False):
                state["ended"] = True
                state["uploading"] = False
                self.uploads.leave()
            return message

        async def tracking_send(message):
            if message["type"] == "http.response.start":
                state["started"] = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyRefused as exc:
            if state["started"]:
                raise
            await error_response(exc.status, exc.code, exc.message, exc.headers)(scope, receive, send)
        finally:
            if state["uploading"]:
                self.uploads.leave()


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
    at a time, so decode threads never compete with onnxruntime's threads. ``clock`` (seconds) times the slots for
    the Retry-After estimate. Use from
    the event loop only::

        gate.check()                      # raises Saturated when the gate is full now (admits nothing)
        ...read and check the body...
        gate.admit()                      # raises Saturated when running + waiting would pass the capacity
        try:
            async with gate.slot() as slot:
                ...decode in threads...
                result = await gate.infer(slot, fn, *args)
        finally:
            gate.leave()
    """

    def __init__(self, max_inflight: int, max_queue: int, on_change=None, clock=time.perf_counter):
        self.max_inflight = max_inflight
        self.capacity = max_inflight + max_queue
        self.admitted = 0
        self.running = 0
        self._slots = asyncio.Semaphore(max_inflight)
        self._executor = ThreadPoolExecutor(max_inflight, thread_name_prefix="occflownet-infer")
        self._mean_s: float | None = None
        self._clock = clock
        self._on_change = on_change or (lambda queued, running: None)

    def _changed(self) -> None:
        self._on_change(self.admitted - self.running, self.running)

    def retry_after(self) -> int:
        """Seconds until a slot is likely free: ⌈mean slot time × (waiting + 1) / slots⌉ in [1, 60], where the
        mean is an exponential moving average (weight 0.2 for the newest slot); 1 before any slot was timed."""
        if self._mean_s is None:
            return 1
        waiting = max(0, self.admitted - self.running) + 1
        return int(min(60, max(1, math.ceil(self._mean_s * waiting / self.max_inflight))))

    def check(self) -> None:
        """Raise Saturated if a request arriving now could not be admitted (nothing is reserved)."""
        if self.admitted >= self.capacity:
            raise Saturated(self.retry_after())

    def admit(self) -> None:
        self.check()
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
        t0 = self._clock()
        self.running += 1
        self._changed()
        held = _Slot()
        try:
            yield held
        finally:
            seconds = self._clock() - t0
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
