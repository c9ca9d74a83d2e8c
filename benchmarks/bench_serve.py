"""Load benchmark of `occflownet serve` on 127.0.0.1 with the real nuScenes frame (six 1600x900 JPEGs + calib.json).

Prints: the direct baseline (JPEG decode of the six images, ``session.run`` on the same decoded arrays, in this
process with the server's thread settings), then throughput and p50/p99 latency at 1, 2, 4 concurrent clients against
a real uvicorn process, the HTTP overhead at one client, and the server's resident memory after 10 and after
``--rss-requests`` requests. Every loop is bounded by a request count and a time limit.

    python benchmarks/bench_serve.py                       # real random-init tiny export if `occflownet export`
                                                           # works, else the fake test model (says which)
    python benchmarks/bench_serve.py --model model.onnx    # any contract-v1 model
    python benchmarks/bench_serve.py --fake                # the fake model of tests/serve_fixtures.py
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FRAME = REPO.parent / "shared" / "data" / "nuscenes-frame"
sys.path.insert(0, str(REPO))

from occflownet.config import CAMERAS  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def pct(values, q):
    return float(np.percentile(np.asarray(values) * 1e3, q))


def get_model(args, workdir: Path) -> tuple[Path, str]:
    if args.model:
        return Path(args.model), f"given model {args.model}"
    if not args.fake:
        out = workdir / "tiny.onnx"
        proc = subprocess.run([sys.executable, "-m", "occflownet", "export", "--preset", "tiny", "--random-init",
                               "--seed", "0", "--out", str(out)], capture_output=True, text=True, cwd=REPO)
        if proc.returncode == 0 and out.is_file():
            return out, "random-init `tiny` export (occflownet export --preset tiny --random-init --seed 0)"
        print(f"# export unavailable ({(proc.stderr or proc.stdout).strip().splitlines()[-1:]}); using the fake model")
    sys.path.insert(0, str(REPO / "tests"))
    from serve_fixtures import build_fake_model
    return build_fake_model(workdir / "fake.onnx"), "FAKE test model (tests/serve_fixtures.py), not a network"


def direct_baseline(model: Path, threads: int, repeats: int) -> dict:
    import cv2

    from serve.calibration import calibration_for_sizes
    from serve.decode import decode_image, stack_images
    from serve.model_runtime import ModelRuntime
    from serve.settings import ServeSettings

    jpegs = {cam: (FRAME / f"{cam}.jpg").read_bytes() for cam in CAMERAS}
    calib = json.loads((FRAME / "calib.json").read_text())
    decode_s = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        images = [decode_image(cam, jpegs[cam], 1 << 30) for cam in CAMERAS]
        decode_s.append(time.perf_counter() - t0)
    cv2_threads = cv2.getNumThreads()
    runtime = ModelRuntime.load(model, ServeSettings(intra_op_threads=threads))
    K, T = calibration_for_sizes(calib, runtime.metadata, [(im.shape[1], im.shape[0]) for im in images])
    stacked, K = stack_images(images, K)
    runtime.infer(stacked, K, T)  # warm-up
    infer_s = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        runtime.infer(stacked, K, T)
        infer_s.append(time.perf_counter() - t0)
    del runtime
    return {"decode_serial_p50_ms": pct(decode_s, 50), "infer_p50_ms": pct(infer_s, 50),
            "infer_p99_ms": pct(infer_s, 99), "cv2_threads": cv2_threads}


def load_level(base: str, files: dict, concurrency: int, max_requests: int, time_limit: float,
               accept: str = "application/octet-stream") -> dict:
    import httpx

    latencies, statuses, lock = [], {}, threading.Lock()
    remaining = [max_requests]
    stop_at = time.monotonic() + time_limit

    def client():
        with httpx.Client(timeout=120) as c:
            while time.monotonic() < stop_at:
                with lock:
                    if remaining[0] <= 0:
                        return
                    remaining[0] -= 1
                t0 = time.perf_counter()
                r = c.post(f"{base}/v1/occupancy", files=files, headers={"Accept": accept})
                dt = time.perf_counter() - t0
                with lock:
                    statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
                    if r.status_code == 200:
                        latencies.append(dt)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=client) for _ in range(concurrency)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    return {"concurrency": concurrency, "ok": len(latencies), "statuses": statuses, "wall_s": wall,
            "throughput_rps": len(latencies) / wall, "p50_ms": pct(latencies, 50) if latencies else float("nan"),
            "p99_ms": pct(latencies, 99) if latencies else float("nan")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model")
    parser.add_argument("--fake", action="store_true", help="use the fake test model")
    parser.add_argument("--requests", type=int, default=40, help="requests per concurrency level")
    parser.add_argument("--time-limit", type=float, default=90.0, help="seconds per concurrency level")
    parser.add_argument("--concurrency", default="1,2,4")
    parser.add_argument("--rss-requests", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=15, help="direct-baseline repetitions")
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: cores)")
    args = parser.parse_args()
    if not FRAME.is_dir():
        print(f"real frame not found at {FRAME}", file=sys.stderr)
        return 2
    from serve.settings import available_cores

    threads = args.threads or available_cores()
    files = {cam: (f"{cam}.jpg", (FRAME / f"{cam}.jpg").read_bytes(), "image/jpeg") for cam in CAMERAS}
    files["calibration"] = ("calib.json", (FRAME / "calib.json").read_bytes(), "application/json")
    levels = [int(c) for c in args.concurrency.split(",")]

    with tempfile.TemporaryDirectory() as tmp:
        model, which = get_model(args, Path(tmp))
        print(f"# model: {which}; {model.stat().st_size / 1e6:.1f} MB; {available_cores()} cores; "
              f"intra-op threads {threads}")
        base_line = direct_baseline(model, threads, args.repeats)
        print(f"direct: decode 6 JPEGs (1600x900, serial) p50 {base_line['decode_serial_p50_ms']:.1f} ms; "
              f"session.run p50 {base_line['infer_p50_ms']:.1f} ms, p99 {base_line['infer_p99_ms']:.1f} ms")

        import httpx

        port = free_port()
        env = os.environ | {"OCCFLOWNET_INTRA_OP_THREADS": str(threads)}
        proc = subprocess.Popen([sys.executable, "-m", "occflownet", "serve", "--model", str(model), "--port",
                                 str(port), "--no-access-log", "--log-level", "warning",
                                 "--max-queue", str(max(levels) + 2)], env=env, cwd=REPO)
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 120
            while True:
                if proc.poll() is not None or time.monotonic() > deadline:
                    print("server did not become ready", file=sys.stderr)
                    return 1
                try:
                    if httpx.get(f"{base}/readyz", timeout=2).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.2)
            first = load_level(base, files, 1, 10, args.time_limit)
            rss_10 = rss_mib(proc.pid)
            done = first["ok"]
            results = []
            for c in levels:
                res = load_level(base, files, c, args.requests, args.time_limit)
                results.append(res)
                done += res["ok"]
                print(f"c={c}: {res['ok']} ok {res['statuses']} in {res['wall_s']:.1f} s: "
                      f"{res['throughput_rps']:.2f} req/s, p50 {res['p50_ms']:.1f} ms, p99 {res['p99_ms']:.1f} ms")
            for accept in ("application/json", "image/png"):
                r = load_level(base, files, 1, 10, args.time_limit, accept)
                done += r["ok"]
                print(f"c=1 Accept {accept}: p50 {r['p50_ms']:.1f} ms")
            c1 = next(r for r in results if r["concurrency"] == 1)
            overhead = c1["p50_ms"] - base_line["infer_p50_ms"] - base_line["decode_serial_p50_ms"]
            print(f"HTTP overhead at c=1 (p50 - session.run p50 - serial decode p50): {overhead:.1f} ms = "
                  f"{100 * overhead / base_line['infer_p50_ms']:.1f} % of session.run "
                  f"(target <= 10 % plus decode)")
            remaining = max(0, args.rss_requests - done)
            t0 = time.monotonic()
            while remaining > 0 and time.monotonic() - t0 < 20 * args.time_limit:
                r = load_level(base, files, 2, min(remaining, 100), args.time_limit)
                remaining -= r["ok"]
                done += r["ok"]
                if r["ok"] == 0:
                    break
            print(f"server RSS: {rss_10:.0f} MiB after 10 requests, {rss_mib(proc.pid):.0f} MiB after {done} requests")
            metrics = httpx.get(f"{base}/metrics").text
            for line in metrics.splitlines():
                if line.startswith("occflownet_stage_duration_seconds_sum") or \
                        line.startswith("occflownet_stage_duration_seconds_count"):
                    print("  " + line)
        finally:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
