"""Can FastAPI's own form handling (``UploadFile`` / ``File`` / ``Form`` parameters) hold the limits of
``serve/form.py``'s streaming reader with the same memory? Peak resident memory and what each answers, per case.

Two minimal servers, each a real uvicorn process on 127.0.0.1 behind the server's own body-size middleware
(``--max-body-mb``, default 64) and error handlers, differing only in how ``POST /v1/occupancy`` reads its body:

- ``reader``: ``occflownet.serve.form.read_parts`` (the server's route): part names checked as each part's headers
  arrive, a byte limit per part (images: the body limit; calibration: 1 MiB), parts kept as bytes;
- ``framework``: six ``UploadFile = File()`` parameters and ``calibration: UploadFile | None = File(None)``:
  Starlette parses the whole form first (parts over 1 MiB spooled to temporary files), then FastAPI validates.

Each case runs in a fresh server process; reported: the answer, the bytes the client got to send, the server's
peak resident memory (VmHWM) minus its resident memory before the request, and the bytes it wrote to temporary
files (peak of the spool folder). Bodies are streamed chunked (no Content-Length), so the middleware counts them.
Prints a markdown table, one row per case and kind as it finishes, with the load average and the float32 matmul
rate; each row also as a JSON line to ``--jsonl``.

    python -m benchmarks.perf.bench_form            # the cases below, a table on stdout
"""

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.harness import Results, add_jsonl_option, module_argv, tree_env
from occflownet.occ3d import CAMERAS
from occflownet.serve.client import wait_ready
from tests.serve_fixtures import free_port

MiB = 1024 * 1024
BOUNDARY = b"b0undary"
CHUNK = 256 * 1024


def make_app(kind: str, max_body: int):
    """The minimal app of one kind (module docstring): answers {"parts": {name: bytes}} or the error shape."""
    from fastapi import FastAPI, File, Request, UploadFile

    from occflownet.serve.errors import add_error_handlers
    from occflownet.serve.form import read_parts
    from occflownet.serve.limits import BodyLimitsMiddleware, Uploads
    from occflownet.serve.routers.occupancy import occupancy_parts

    app = FastAPI()
    add_error_handlers(app)
    app.add_middleware(BodyLimitsMiddleware, max_bytes=max_body, uploads=Uploads(32, 300.0))
    app.get("/readyz")(lambda: {"status": "ready"})
    if kind == "reader":
        @app.post("/v1/occupancy")
        async def reader(request: Request):
            parts = await read_parts(request, occupancy_parts(CAMERAS, max_body))
            return {"parts": {name: len(p.data) for name, p in parts.items()}}
    else:
        @app.post("/v1/occupancy")
        async def framework(CAM_FRONT: UploadFile = File(), CAM_FRONT_RIGHT: UploadFile = File(),  # noqa: N803
                            CAM_FRONT_LEFT: UploadFile = File(), CAM_BACK: UploadFile = File(),  # noqa: N803
                            CAM_BACK_LEFT: UploadFile = File(), CAM_BACK_RIGHT: UploadFile = File(),  # noqa: N803
                            calibration: UploadFile | None = File(None)):
            files = dict(zip(CAMERAS, (CAM_FRONT, CAM_FRONT_RIGHT, CAM_FRONT_LEFT, CAM_BACK, CAM_BACK_LEFT,
                                       CAM_BACK_RIGHT))) | ({"calibration": calibration} if calibration else {})
            return {"parts": {name: len(await f.read()) for name, f in files.items()}}
    return app


def serve(kind: str, port: int, max_body: int) -> None:
    import uvicorn

    uvicorn.run(make_app(kind, max_body), host="127.0.0.1", port=port, log_level="warning", access_log=False)


# ---------------------------------------------------------------- the client side

def part(name: str, size: int, filename: str | None = "x.jpg") -> list[bytes]:
    """One multipart part of ``size`` zero bytes, as a header and data chunks."""
    disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
    head = b"--" + BOUNDARY + b"\r\nContent-Disposition: " + disposition.encode() + b"\r\n\r\n"
    chunks = [head] + [b"\0" * min(CHUNK, size - o) for o in range(0, size, CHUNK)]
    return chunks + [b"\r\n"]


def body(parts: list[list[bytes]]) -> list[bytes]:
    return [c for p in parts for c in p] + [b"--" + BOUNDARY + b"--\r\n"]


CASES = {
    "valid, 6 x 1 MiB images": lambda: body([part(c, MiB) for c in CAMERAS]),
    "valid, 6 x 10 MiB images (60 MiB)": lambda: body([part(c, 10 * MiB) for c in CAMERAS]),
    "oversized: 6 x 20 MiB (120 MiB, limit 64)": lambda: body([part(c, 20 * MiB) for c in CAMERAS]),
    "unexpected 40 MiB part first": lambda: body([part("EXTRA", 40 * MiB)] + [part(c, MiB) for c in CAMERAS]),
    "20,000 one-byte parts": lambda: body([part(f"p{i}", 1, None) for i in range(20_000)]),
    "8 MiB calibration part": lambda: body([part(c, MiB) for c in CAMERAS] + [part("calibration", 8 * MiB)]),
}


def _memory(pid: int) -> dict[str, int]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) * 1024
    return fields


def _spooled_bytes(pid: int, folder: Path) -> int:
    """Bytes in the server's open files under ``folder`` (Starlette's spool files are unnamed O_TMPFILE files:
    seen only through the process's file descriptors)."""
    total = 0
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            if os.readlink(fd).startswith(str(folder)):
                total += os.stat(fd).st_size
        except OSError:
            pass
    return total


def run_case(kind: str, name: str, max_body: int) -> dict:
    """One case against a fresh server of ``kind`` → answer, bytes sent, peak RSS growth, peak temp-file bytes."""
    import httpx

    port = free_port()
    spool = Path(tempfile.mkdtemp(prefix="bench-form-"))
    proc = subprocess.Popen([*module_argv(__spec__.name), "--serve", kind, "--port", str(port), "--max-body",
                             str(max_body)], env=tree_env(TMPDIR=str(spool)))
    sent, peak_tmp, stop = 0, 0, threading.Event()

    def watch_tmp():
        nonlocal peak_tmp
        while not stop.is_set():
            peak_tmp = max(peak_tmp, _spooled_bytes(proc.pid, spool))
            time.sleep(0.005)

    try:
        wait_ready(f"http://127.0.0.1:{port}", 30, proc)
        before = _memory(proc.pid)["VmRSS"]
        chunks = CASES[name]()

        def stream():
            nonlocal sent
            for c in chunks:
                sent += len(c)
                yield c

        watcher = threading.Thread(target=watch_tmp, daemon=True)
        watcher.start()
        t0 = time.perf_counter()
        try:
            r = httpx.post(f"http://127.0.0.1:{port}/v1/occupancy", content=stream(), timeout=120,
                           headers={"Content-Type": f"multipart/form-data; boundary={BOUNDARY.decode()}"})
            answer = f"{r.status_code} {r.text[:90]}"
        except httpx.HTTPError as exc:
            answer = f"connection closed ({type(exc).__name__})"
        seconds = time.perf_counter() - t0
        time.sleep(0.1)
        stop.set()
        watcher.join()
        peak = _memory(proc.pid)["VmHWM"]
        return {"answer": answer, "sent": sent, "rss_growth": max(0, peak - before), "tmp": peak_tmp,
                "seconds": seconds, "rss_before": before}
    finally:
        stop.set()
        proc.terminate()
        proc.wait(20)
        for p in spool.iterdir():
            p.unlink()
        spool.rmdir()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--serve", choices=["reader", "framework"], help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, help=argparse.SUPPRESS)
    p.add_argument("--max-body", type=int, default=64 * MiB, help="body limit in bytes (default 64 MiB)")
    add_jsonl_option(p)
    args = p.parse_args(argv)
    if args.serve:
        serve(args.serve, args.port, args.max_body)
        return 0
    results = Results("bench_form", args.jsonl)
    print("| case | form handling | answer | sent | peak RSS growth | temp files | time | machine |")
    print("|---|---|---|---:|---:|---:|---:|---|")
    for name in CASES:
        for kind in ("reader", "framework"):
            r = run_case(kind, name, args.max_body)
            results.add({"case": name, "kind": kind, **r},
                        f"| {name} | {kind} | {r['answer']} | {r['sent'] / MiB:.1f} MiB | "
                        f"{r['rss_growth'] / MiB:.1f} MiB | {r['tmp'] / MiB:.1f} MiB | {r['seconds']:.2f} s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
