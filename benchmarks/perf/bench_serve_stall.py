"""Stalled uploads against `occflownet serve` on 127.0.0.1: what a valid request gets while they hang, when they are
answered, and how long SIGTERM takes with them connected.

Starts `occflownet serve` (a real uvicorn process; the fake test model unless ``--model``), then:
1. ``--requests`` valid requests (six 96×54 PNGs) with no other client: status and latency;
2. ``--stalled`` connections that each send the headers of a ``POST /v1/occupancy`` (Content-Length 1 MB) and
   1,000 bytes of its body, then nothing; once the server counts them, the same valid requests again;
3. when the stalled connections are answered (the body deadline) and with what;
4. ``--stalled`` new stalled connections, then SIGTERM: how long until the process has exited, and what they got.
Every wait is bounded (60 s, or the body deadline plus 30 s). Each line ends with the load average and the float32
matmul rate; the lines are appended to ``--jsonl`` as they come.

    python -m benchmarks.perf.bench_serve_stall                       # defaults: 5 stalled, body timeout 30 s
    python -m benchmarks.perf.bench_serve_stall --workers 2 --body-timeout 5
"""
from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import REPO, Results, add_jsonl_option, tree_env
from occflownet.serve.client import wait_ready
from tests.serve_fixtures import (build_fake_model, free_port, image_files, metric_samples, read_answer,
                                  stalled_upload, stop_server, synthetic_images)


def valid_requests(base: str, count: int) -> str:
    """``count`` valid requests one after another → "status latency" of each."""
    import httpx

    files = image_files(synthetic_images((96, 54)))
    out = []
    for _ in range(count):
        t0 = time.perf_counter()
        r = httpx.post(f"{base}/v1/occupancy", files=files, headers={"Accept": "application/octet-stream"},
                       timeout=60)
        out.append(f"{r.status_code} {(time.perf_counter() - t0) * 1e3:.0f} ms"
                   + ("" if r.status_code == 200 else f" {r.json()['error']['code']}"))
    return ", ".join(out)


def stall(base: str, port: int, count: int) -> list:
    """``count`` stalled uploads, returned once the server counts them (or after 20 s)."""
    import httpx

    socks = [stalled_upload(port) for _ in range(count)]
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        text = httpx.get(f"{base}/metrics", timeout=10).text
        if metric_samples(text).get(("occflownet_uploads_in_progress", ()), 0) >= count:
            break
        time.sleep(0.05)
    return socks


def status_line(answer: bytes) -> str:
    if not answer:
        return "nothing"
    head, _, body = answer.partition(b"\r\n\r\n")
    return head.split(b"\r\n", 1)[0].decode() + " " + body[:60].decode(errors="replace")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="contract-v1 ONNX model (default: the fake test model)")
    parser.add_argument("--stalled", type=int, default=5)
    parser.add_argument("--requests", type=int, default=3)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--body-timeout", type=float, default=30.0)
    add_jsonl_option(parser)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-serve-stall-") as work:
        run(args, Path(work))


def run(args, work: Path) -> None:
    results = Results("bench_serve_stall", args.jsonl)
    model = Path(args.model) if args.model else build_fake_model(work / "fake.onnx")
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "occflownet", "serve", "--model", str(model), "--port", str(port),
                             "--workers", str(args.workers), "--body-timeout", str(args.body_timeout),
                             "--no-access-log", "--log-level", "warning"], cwd=REPO,
                            env=tree_env(PROMETHEUS_MULTIPROC_DIR=str(work / "metrics")))
    try:
        wait_ready(base, 60, proc)
        print(f"model {model.name}, {args.workers} worker(s), body timeout {args.body_timeout:g} s")
        alone = valid_requests(base, args.requests)
        results.add({"phase": "no other client", "requests": alone}, f"no other client:        {alone}")
        socks = stall(base, port, args.stalled)
        t_stall = time.monotonic()
        stalled = valid_requests(base, args.requests)
        results.add({"phase": "uploads stalled", "stalled": args.stalled, "requests": stalled},
                    f"{args.stalled} uploads stalled:    {stalled}")
        answers = [read_answer(s, args.body_timeout + 30 - (time.monotonic() - t_stall)) for s in socks]
        after, answer = time.monotonic() - t_stall, status_line(answers[0])
        results.add({"phase": "stalled answered", "seconds": after, "answer": answer},
                    f"stalled uploads answered {after:.1f} s after they stalled: {answer}")
        socks = stall(base, port, args.stalled)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
        exited, answer = time.monotonic() - t0, status_line(read_answer(socks[0], 5))
        results.add({"phase": "SIGTERM", "stalled": args.stalled, "seconds": exited, "answer": answer},
                    f"SIGTERM with {args.stalled} stalled uploads: exited after {exited:.2f} s; they got {answer}")
    finally:
        stop_server(proc)


if __name__ == "__main__":
    main()
