"""Load benchmark of `occflownet serve` on 127.0.0.1 with the real nuScenes frame (six 1600x900 JPEGs + calib.json).

1. Starts `occflownet serve` (a real uvicorn process) and, in this process, an onnxruntime session on the same model
   with the same thread settings, on the same decoded arrays.
2. Interleaved phase (one client): direct JPEG decode, direct ``session.run`` and one HTTP request, in turn
   (``benchmarks.harness.interleaved``), so machine noise (the 2-core machine is shared) hits all sides alike. Reports the HTTP overhead two ways: paired
   (client latency minus the server's own decode/queue/inference/encode times of that request, from its
   Server-Timing header) and against the direct run (p50 HTTP - p50 session.run - p50 server decode).
3. Throughput and p50/p99 latency at 1, 2, 4 concurrent clients (client threads share the machine with the server).
4. Resident memory of the server after 10 and after ``--rss-requests`` requests; B=2 vs two B=1 runs (micro-batching).
Every loop is bounded by a request count and a time limit. Each figure's line ends with the load average and the
float32 matmul rate; the figures are appended to ``--jsonl`` as they come.

    python -m benchmarks.perf.bench_serve                       # real random-init tiny export if `occflownet
                                                                # export` works, else the fake test model (says which)
    python -m benchmarks.perf.bench_serve --model model.onnx    # any contract-v1 model
    python -m benchmarks.perf.bench_serve --fake                # the fake model of tests/serve_fixtures.py
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import REPO, SHARED_DATA, Results, add_jsonl_option, interleaved, tree_env
from occflownet.occ3d import CAMERAS
from occflownet.serve.client import wait_ready
from tests.serve_fixtures import free_port

FRAME = SHARED_DATA / "nuscenes-frame"


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def p(values, q) -> float:
    return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")


def server_timing(headers) -> dict[str, float]:
    out = {}
    for item in headers.get("server-timing", "").split(","):
        name, _, dur = item.strip().partition(";dur=")
        if dur:
            out[name] = float(dur)
    return out


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
    from tests.serve_fixtures import build_fake_model
    return build_fake_model(workdir / "fake.onnx"), "FAKE test model (tests/serve_fixtures.py), not a network"


class Direct:
    """The same work without HTTP: decode the six JPEGs, run the model on the decoded arrays (this process), through
    the server's own runtime (``ModelRuntime.frame`` → ``FrameCalibration.inputs`` → ``infer``)."""

    def __init__(self, model: Path, threads: int):
        from occflownet.serve.model_runtime import ModelRuntime
        from occflownet.serve.settings import ServeSettings

        self.jpegs = {cam: (FRAME / f"{cam}.jpg").read_bytes() for cam in CAMERAS}
        self.runtime = ModelRuntime.load(model, ServeSettings(intra_op_threads=threads))
        self.images = np.stack(self.decode())                                  # uint8 [6, 900, 1600, 3] RGB
        calib = (FRAME / "calib.json").read_bytes()
        self.inputs = self.runtime.frame(calib, [(1600, 900)] * 6).inputs(self.images)
        for _ in range(3):
            self.infer()

    def decode(self):
        from occflownet.serve.decode import decode_image
        return [decode_image(cam, self.jpegs[cam], 1 << 30) for cam in CAMERAS]

    def infer(self):
        return self.runtime.infer(self.inputs)

    def batch2(self):
        from occflownet.runtime import ModelInputs

        return self.runtime.predictor.predict(ModelInputs.stack([self.inputs] * 2), ("occupancy",))


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def load_level(base: str, files: dict, concurrency: int, max_requests: int, time_limit: float,
               accept: str = "application/octet-stream") -> dict:
    import httpx

    latencies, statuses, lock, stages = [], {}, threading.Lock(), {}
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
                dt = (time.perf_counter() - t0) * 1e3
                with lock:
                    statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
                    if r.status_code == 200:
                        latencies.append(dt)
                        for name, ms in server_timing(r.headers).items():
                            stages.setdefault(name, []).append(ms)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=client) for _ in range(concurrency)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    return {"concurrency": concurrency, "ok": len(latencies), "statuses": statuses, "wall_s": wall,
            "rps": len(latencies) / wall, "p50": p(latencies, 50), "p99": p(latencies, 99),
            "stages": {k: p(v, 50) for k, v in stages.items()}}


def http_vs_direct(base: str, files: dict, direct: Direct, n: int, results: Results) -> None:
    """``n`` interleaved rounds of direct decode, direct session.run and one HTTP request → the HTTP overhead."""
    import httpx

    with httpx.Client(timeout=120) as c:
        def request():
            r = c.post(f"{base}/v1/occupancy", files=files, headers={"Accept": "application/octet-stream"})
            assert r.status_code == 200, r.text
            return server_timing(r.headers)

        runs = interleaved({"decode": direct.decode, "run": direct.infer, "http": request}, n)
    rows = {k: [1e3 * seconds for seconds, _ in v] for k, v in runs.items()}
    timings = [st for _, st in runs["http"]]
    rows["paired"] = [ms - sum(st.values()) for ms, st in zip(rows["http"], timings)]
    rows["server_decode"] = [st["decode"] for st in timings]
    rows["server_inference"] = [st["inference"] for st in timings]
    m = {k: p(v, 50) for k, v in rows.items()}
    vs_direct = m["http"] - m["run"] - m["server_decode"]
    results.add({"phase": "interleaved", "rounds": n, "p50_ms": m, "paired_p99_ms": p(rows["paired"], 99),
                 "overhead_vs_direct_ms": vs_direct},
                f"interleaved, 1 client, {n} rounds (p50 ms): direct serial decode {m['decode']:.1f}, direct "
                f"session.run {m['run']:.1f} | HTTP request {m['http']:.1f} = server decode (6 threads) "
                f"{m['server_decode']:.1f} + inference {m['server_inference']:.1f} + rest\n"
                f"HTTP overhead, paired (latency - server-side stages): p50 {m['paired']:.1f} ms, "
                f"p99 {p(rows['paired'], 99):.1f} ms = {100 * m['paired'] / m['run']:.1f} % of session.run\n"
                f"HTTP overhead vs direct (p50 HTTP - p50 session.run - p50 server decode): {vs_direct:.1f} ms = "
                f"{100 * vs_direct / m['run']:.1f} % of session.run (target <= 10 % plus decode)")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model")
    parser.add_argument("--fake", action="store_true", help="use the fake test model")
    parser.add_argument("--requests", type=int, default=40, help="requests per concurrency level")
    parser.add_argument("--rounds", type=int, default=20, help="rounds of the interleaved phase")
    parser.add_argument("--time-limit", type=float, default=90.0, help="seconds per phase")
    parser.add_argument("--concurrency", default="1,2,4")
    parser.add_argument("--rss-requests", type=int, default=500)
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: cores)")
    add_jsonl_option(parser)
    return parser.parse_args()


def start_server(model: Path, threads: int, max_queue: int) -> tuple[subprocess.Popen, str]:
    """`occflownet serve` on a free 127.0.0.1 port → (its process, base URL), once /readyz answers 200."""
    port = free_port()
    env = tree_env(OCCFLOWNET_INTRA_OP_THREADS=str(threads))
    proc = subprocess.Popen([sys.executable, "-m", "occflownet", "serve", "--model", str(model), "--port", str(port),
                             "--no-access-log", "--log-level", "warning", "--max-queue", str(max_queue)],
                            env=env, cwd=REPO)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_ready(base, timeout=120, proc=proc, interval=0.2)
    except BaseException:
        proc.terminate()
        proc.wait(30)
        raise
    return proc, base


def direct_phases(base: str, files: dict, model: Path, threads: int, rounds: int, results: Results) -> None:
    """The interleaved HTTP-vs-direct comparison, then micro-batching (B=2 vs two B=1 runs) on the direct session."""
    direct = Direct(model, threads)
    http_vs_direct(base, files, direct, rounds, results)
    one = [timed(direct.infer) for _ in range(5)]
    two = [timed(direct.batch2) for _ in range(5)]
    results.add({"phase": "micro-batching", "b1_p50_ms": p(one, 50), "b2_p50_ms": p(two, 50)},
                f"micro-batching: session.run B=2 p50 {p(two, 50):.1f} ms vs B=1 {p(one, 50):.1f} ms "
                f"({p(two, 50) / (2 * p(one, 50)):.2f} x two B=1 runs)")


def load_phases(base: str, files: dict, levels: list[int], args, results: Results) -> int:
    """Throughput and latency per concurrency level, then JSON and PNG answers at one client → requests done."""
    done = 0
    for c in levels:
        res = load_level(base, files, c, args.requests, args.time_limit)
        done += res["ok"]
        stages = ", ".join(f"{k} {v:.1f}" for k, v in res["stages"].items())
        results.add({"phase": "load", **res}, f"c={c}: {res['ok']} ok {res['statuses']} in {res['wall_s']:.1f} s: "
                    f"{res['rps']:.2f} req/s, p50 {res['p50']:.1f} ms, p99 {res['p99']:.1f} ms; server-side p50 (ms): "
                    f"{stages}")
    for accept in ("application/json", "image/png"):
        r = load_level(base, files, 1, 10, args.time_limit, accept)
        done += r["ok"]
        results.add({"phase": "answer format", "accept": accept, **r},
                    f"c=1 Accept {accept}: p50 {r['p50']:.1f} ms, server encode p50 {r['stages']['encode']:.1f} ms")
    return done


def load_until(base: str, files: dict, done: int, total: int, time_limit: float) -> int:
    """Two clients until ``total`` requests are done (for the memory figure), bounded in time → requests done."""
    t0 = time.monotonic()
    while done < total and time.monotonic() - t0 < 20 * time_limit:
        r = load_level(base, files, 2, min(total - done, 100), time_limit)
        done += r["ok"]
        if r["ok"] == 0:
            break
    return done


def server_means(base: str, results: Results) -> None:
    """Mean server-side time per stage over every request, from the server's own /metrics histograms."""
    import httpx

    text = httpx.get(f"{base}/metrics").text
    sums = {line.split('"')[1]: float(line.split()[-1]) for line in text.splitlines()
            if line.startswith("occflownet_stage_duration_seconds_sum")}
    count = next(float(line.split()[-1]) for line in text.splitlines()
                 if line.startswith('occflownet_stage_duration_seconds_count{stage="inference"}'))
    means = {k: 1e3 * v / count for k, v in sums.items()}
    results.add({"phase": "server means", "ms": means},
                "server means over all requests (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in means.items()))


def run_benchmark(args, model: Path, threads: int, results: Results) -> None:
    """Every phase against one server process (module docstring), in order."""
    files = {cam: (f"{cam}.jpg", (FRAME / f"{cam}.jpg").read_bytes(), "image/jpeg") for cam in CAMERAS}
    files["calibration"] = ("calib.json", (FRAME / "calib.json").read_bytes(), "application/json")
    levels = [int(c) for c in args.concurrency.split(",")]
    proc, base = start_server(model, threads, max(levels) + 2)
    try:
        first = load_level(base, files, 1, 10, args.time_limit)
        rss_10, done = rss_mib(proc.pid), first["ok"]
        direct_phases(base, files, model, threads, args.rounds, results)
        done += args.rounds
        done += load_phases(base, files, levels, args, results)
        done = load_until(base, files, done, args.rss_requests, args.time_limit)
        rss = rss_mib(proc.pid)
        results.add({"phase": "memory", "rss_mib_after_10": rss_10, "rss_mib": rss, "requests": done},
                    f"server RSS: {rss_10:.0f} MiB after 10 requests, {rss:.0f} MiB after {done} requests")
        server_means(base, results)
    finally:
        proc.terminate()
        proc.wait(30)


def main() -> int:
    args = parse_args()
    if not FRAME.is_dir():
        print(f"real frame not found at {FRAME}", file=sys.stderr)
        return 2
    from occflownet.serve.malloc import cap_malloc_arenas
    from occflownet.serve.settings import available_cores

    cap_malloc_arenas()  # as the server does
    threads = args.threads or available_cores()
    with tempfile.TemporaryDirectory() as tmp:
        model, which = get_model(args, Path(tmp))
        results = Results("bench_serve", args.jsonl)
        results.note(f"# model: {which}; {model.stat().st_size / 1e6:.1f} MB; {available_cores()} cores; intra-op "
                     f"threads {threads}")
        run_benchmark(args, model, threads, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
