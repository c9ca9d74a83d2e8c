"""Client-side helper for a running server: wait until it is ready. Standard library only (no httpx needed).

    from occflownet.serve.client import wait_ready
    wait_ready("http://127.0.0.1:8000", timeout=60)        # → {"status": "ready", "warmup_seconds": ...}

Used by the tests' server fixtures, ``benchmarks/perf/bench_serve.py`` and ``docker/probe.py``.
"""
from __future__ import annotations

import http.client
import json
import time
import urllib.error
import urllib.request
from collections.abc import Callable


class ServerNotReady(RuntimeError):
    """The server did not answer 200 within the timeout, or its process exited first."""


def http_get(url: str, timeout: float = 2.0) -> tuple[int, bytes]:
    """``GET url`` → (status, body), an error status included; OSError when nothing answers."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def wait_ready(url: str, timeout: float = 30.0, proc=None, path: str = "/readyz", interval: float = 0.05,
               get: Callable[[str], tuple[int, bytes]] = http_get) -> dict:
    """Poll ``GET {url}{path}`` every ``interval`` seconds until it answers 200 → its JSON body.

    ``proc`` (the server's ``subprocess.Popen``, optional): fail as soon as it exits, with its stderr when piped.
    ``get`` replaces the HTTP GET: ``get(url + path) -> (status, body bytes)`` (e.g. an in-process test client
    with ``url=""``). Raises :class:`ServerNotReady` after ``timeout`` seconds, naming the last answer."""
    deadline = time.monotonic() + timeout
    last = "no answer"
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            stderr = proc.stderr.read() if proc.stderr is not None else ""
            raise ServerNotReady(f"server exited with status {proc.returncode} before {url}{path} answered 200"
                                 + (f": {stderr}" if stderr else ""))
        try:
            status, body = get(url + path)
        except (OSError, http.client.HTTPException) as exc:  # not listening yet, connection reset, timeout
            last = f"{type(exc).__name__}: {exc}"
        else:
            if status == 200:
                return json.loads(body)
            last = f"{status} {body[:200].decode('utf-8', 'replace')}"
        time.sleep(interval)
    raise ServerNotReady(f"{url}{path} did not answer 200 within {timeout:g} s (last: {last})")
