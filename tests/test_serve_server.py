"""The app under a real uvicorn server on 127.0.0.1: saturation (503 + Retry-After), body limits on the wire,
and the ``occflownet serve`` command (one and two workers, bad model file)."""
import os
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest
from serve_fixtures import (build_fake_model, free_port, image_files, metric_samples, running_server, stop_server,
                            synthetic_images)

from occflownet.serve.app import create_app
from occflownet.serve.client import wait_ready
from occflownet.serve.model_runtime import ModelRuntime
from occflownet.serve.settings import ServeSettings

REPO = Path(__file__).resolve().parents[1]
IMAGES = synthetic_images((96, 54))


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return build_fake_model(tmp_path_factory.mktemp("serve-server") / "fake.onnx")


def post_ok(base: str, **kw) -> np.ndarray:
    r = httpx.post(f"{base}/v1/occupancy", files=image_files(IMAGES), headers={"Accept": "application/x-npy"},
                   timeout=30, **kw)
    assert r.status_code == 200, r.text
    import io
    return np.load(io.BytesIO(r.content))


def test_saturation_gives_503_with_retry_after_then_recovers(model_path):
    settings = ServeSettings(model_path=str(model_path), max_inflight=1, max_queue=1)
    runtime = ModelRuntime.load(model_path, settings)
    runtime.warm_up()                                                       # before infer is made to block
    gate_open = threading.Event()
    real_infer = runtime.infer
    runtime.infer = lambda *a: (gate_open.wait(20), real_infer(*a))[1]      # an inference that waits to be let go
    with running_server(create_app(settings, runtime=runtime)) as base:
        wait_ready(base)
        with ThreadPoolExecutor(2) as pool:
            held = [pool.submit(post_ok, base) for _ in range(2)]         # one running, one queued
            deadline = time.monotonic() + 20
            while "occflownet_inference_queue_depth 1" not in httpx.get(f"{base}/metrics").text:
                assert time.monotonic() < deadline, "the two requests never filled the gate"
                time.sleep(0.01)
            assert "occflownet_inferences_running 1" in httpx.get(f"{base}/metrics").text
            r = httpx.post(f"{base}/v1/occupancy", files=image_files(IMAGES), timeout=10)
            assert r.status_code == 503, r.text
            assert r.json()["error"]["code"] == "saturated" and int(r.headers["retry-after"]) >= 1
            assert httpx.get(f"{base}/healthz").status_code == 200            # probes still answer
            gate_open.set()
            grids = [f.result(timeout=30) for f in held]
        np.testing.assert_array_equal(grids[0], grids[1])
        np.testing.assert_array_equal(post_ok(base), grids[0])              # and the server recovered
        assert 'occflownet_rejected_total{reason="saturated"} 1' in httpx.get(f"{base}/metrics").text


def _raw_exchange(port: int, head: bytes, chunks=(), chunk_pause: float = 0.0) -> tuple[bytes, int]:
    """Send ``head`` then ``chunks`` until the server answers or closes → (response bytes, body bytes sent)."""
    sent = 0
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(head)
        sock.setblocking(False)
        response = b""
        for chunk in chunks:
            try:
                response += sock.recv(65536)
            except BlockingIOError:
                pass
            if response:
                break
            try:
                sock.sendall(chunk)
                sent += len(chunk)
            except (BlockingIOError, BrokenPipeError, ConnectionResetError):
                break
            time.sleep(chunk_pause)
        sock.setblocking(True)
        try:
            while b"\r\n\r\n" not in response:
                data = sock.recv(65536)
                if not data:
                    break
                response += data
        except ConnectionResetError:
            pass
    return response, sent


def test_body_limit_on_the_wire(model_path):
    limit = 1_000_000
    app = create_app(ServeSettings(model_path=str(model_path), max_body_bytes=limit))
    with running_server(app) as base:
        wait_ready(base)
        port = int(base.rsplit(":", 1)[1])
        head = (b"POST /v1/occupancy HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n")
        # declared too large: answered before a single body byte is sent
        response, _ = _raw_exchange(port, head + b"Content-Length: 50000000000\r\n\r\n")
        assert response.startswith(b"HTTP/1.1 413"), response[:200]
        assert b"connection: close" in response.lower()
        # chunked, no length: refused once the streamed count passes the limit, long before 20 MB are sent
        part = b'--b\r\nContent-Disposition: form-data; name="CAM_FRONT"; filename="f.jpg"\r\n\r\n'
        chunks = [b"%x\r\n%s\r\n" % (len(part), part)] + [b"10000\r\n" + b"\0" * 0x10000 + b"\r\n"] * 320
        response, sent = _raw_exchange(port, head + b"Transfer-Encoding: chunked\r\n\r\n", chunks, 0.002)
        assert response.startswith(b"HTTP/1.1 413"), response[:200]
        assert sent < 3 * limit, f"server let {sent} bytes through before refusing"
        post_ok(base)                                                       # still serving


def _serve_cmd(*args) -> list[str]:
    return [sys.executable, "-m", "occflownet", "serve", *args]


def test_cli_refuses_a_missing_model_naming_it(tmp_path):
    missing = tmp_path / "nope.onnx"
    proc = subprocess.run(_serve_cmd("--model", str(missing), "--port", str(free_port())), capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and f"model file not found: {missing}" in proc.stderr
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"\x08\x07garbage")
    proc = subprocess.run(_serve_cmd("--model", str(broken)), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and f"cannot load model {broken}" in proc.stderr


@pytest.mark.parametrize("workers", [1, 2])
def test_cli_serves_with_workers(model_path, workers):
    port = free_port()
    env = os.environ | {"OCCFLOWNET_MODEL": str(model_path), "OCCFLOWNET_API_KEY": "k"}
    proc = subprocess.Popen(_serve_cmd("--port", str(port), "--workers", str(workers), "--no-access-log"), env=env,
                            cwd=REPO, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        base = f"http://127.0.0.1:{port}"
        wait_ready(base, 60, proc)
        assert httpx.get(f"{base}/v1/metadata", timeout=5).status_code == 401
        md = httpx.get(f"{base}/v1/metadata", headers={"Authorization": "Bearer k"}, timeout=5).json()
        assert md["limits"]["max_queue"] == 4 and md["model"]["file"] == "fake.onnx"
        headers = {"Accept": "application/octet-stream", "Authorization": "Bearer k"}
        grids = [np.frombuffer(httpx.post(f"{base}/v1/occupancy", files=image_files(IMAGES), headers=headers,
                                          timeout=30).content, np.uint8) for _ in range(3)]
        assert all(g.size == 640_000 and np.array_equal(g, grids[0]) for g in grids)
    finally:
        stop_server(proc)
    assert proc.returncode in (0, -15), proc.stderr.read()


def _requests_by_worker(folder: Path) -> dict[int, float]:
    """{worker pid: POST /v1/occupancy 200 answers} from the multiprocess metric files each worker writes."""
    from prometheus_client.mmap_dict import MmapedDict

    counts = {}
    for path in folder.glob("counter_*.db"):
        pid = int(path.stem.split("_")[-1])
        counts[pid] = sum(value for key, value, *_ in MmapedDict.read_all_values_from_file(str(path))
                          if '"occflownet_http_requests_total"' in key and '"/v1/occupancy"' in key
                          and '"200"' in key)
    return counts


def test_metrics_with_two_workers_are_one_scrape(model_path, tmp_path):
    """After requests that reached both workers, every scrape (whichever worker answers) counts all of them."""
    folder = tmp_path / "metrics"
    port = free_port()
    env = os.environ | {"OCCFLOWNET_MODEL": str(model_path), "PROMETHEUS_MULTIPROC_DIR": str(folder)}
    proc = subprocess.Popen(_serve_cmd("--port", str(port), "--workers", "2", "--threads", "1", "--no-access-log"),
                            env=env, cwd=REPO, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    base = f"http://127.0.0.1:{port}"
    sent = 0
    try:
        wait_ready(base, 60, proc)
        headers = {"Accept": "application/octet-stream", "Connection": "close"}  # a new connection per request
        def post(_) -> int:
            # /readyz answered from one worker; the other may still run its warm-up: its 503 not_ready (with
            # Retry-After) is retried, as a client does, and counts nowhere (no 200, no inference)
            for _attempt in range(60):
                answer = httpx.post(f"{base}/v1/occupancy", files=image_files(IMAGES), headers=headers, timeout=30)
                if answer.status_code != 503 or answer.json().get("error", {}).get("code") != "not_ready":
                    return answer.status_code
                time.sleep(float(answer.headers.get("Retry-After", "1")))
            return answer.status_code

        with ThreadPoolExecutor(4) as pool:
            while sent < 64 and sum(n > 0 for n in _requests_by_worker(folder).values()) < 2:
                answers = list(pool.map(post, range(8)))
                assert answers == [200] * 8
                sent += 8
        by_worker = _requests_by_worker(folder)
        assert len([n for n in by_worker.values() if n > 0]) == 2, by_worker   # both workers answered some
        for _ in range(6):                                                      # scrapes reach either worker
            samples = metric_samples(httpx.get(f"{base}/metrics", headers={"Connection": "close"}, timeout=5).text)
            post = (("method", "POST"), ("route", "/v1/occupancy"), ("status", "200"))
            assert samples[("occflownet_http_requests_total", post)] == sent
            inference = samples[("occflownet_stage_duration_seconds_count", (("stage", "inference"),))]
            assert inference == sent                                            # (warm-ups are not observed)
            assert samples[("occflownet_model_ready", ())] == 1
    finally:
        stop_server(proc)
    assert proc.returncode in (0, -15), proc.stderr.read()
    assert folder.is_dir() and not list(folder.glob("*.db"))                   # emptied when the server ended
