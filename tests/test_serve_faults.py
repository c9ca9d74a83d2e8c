"""The server's fault battery: what clients and operators did to it, each reproduced against a real server.

Stalled and slow uploads (raw sockets against uvicorn on 127.0.0.1): a valid request is served while five uploads
stall; a stalled or dripping body gets 408 and its connection is closed; more uploads than ``max_uploads`` get
503 ``busy``; SIGTERM ends the stalled uploads, finishes the work in flight and exits (in process, and the
``occflownet serve`` command with one and two workers). Process: ``kill -9`` of the supervisor of
``--workers 2`` stops its workers; an unreadable model is named "permission denied"; a bad port, a port in use and
an execution provider onnxruntime lacks each end the command with one line. Answers: an unhandled error is logged
once and answered 500 in the error shape; a calibration that breaks its parser answers 400; every answer carries
``X-Content-Type-Options: nosniff``; ``/docs`` and ``/redoc`` are off unless asked for.

No timed assertions: a wait that must end (an answer, an exit) has a bound far above what it takes; what it takes
is measured by ``benchmarks/perf/bench_serve_stall.py``.
"""
from __future__ import annotations

import ctypes
import json
import logging
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvicorn
from serve_fixtures import (build_fake_model, fake_reference, free_port, image_files, metric_samples, read_answer,
                            running_server, stalled_upload, stop_server, synthetic_images)
from starlette.testclient import TestClient

from occflownet.contract import validate_calibration
from occflownet.occ3d import CAMERAS
from occflownet.rig import default_rig
from occflownet.serve.app import create_app
from occflownet.serve.client import wait_ready
from occflownet.serve.model_runtime import ModelRuntime
from occflownet.serve.settings import ServeSettings

REPO = Path(__file__).resolve().parents[1]
IMAGES = synthetic_images((96, 54))
OCTET = {"Accept": "application/octet-stream"}


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return build_fake_model(tmp_path_factory.mktemp("serve-faults") / "fake.onnx")


def expected_grid() -> np.ndarray:
    K, T = validate_calibration(default_rig(480, 270), CAMERAS).arrays_for([(96, 54)] * 6)
    return fake_reference(np.stack(IMAGES), K, T)


def post(base: str, timeout: float = 60) -> httpx.Response:
    return httpx.post(f"{base}/v1/occupancy", files=image_files(IMAGES), headers=OCTET, timeout=timeout)


def assert_grid(response: httpx.Response) -> None:
    assert response.status_code == 200, response.text
    np.testing.assert_array_equal(np.frombuffer(response.content, np.uint8).reshape(200, 200, 16), expected_grid())


def gauge(base: str, name: str) -> float:
    return metric_samples(httpx.get(f"{base}/metrics", timeout=10).text).get((name, ()), -1.0)


def wait_for_requests(base: str, count: int, timeout: float = 90) -> None:
    """Until the server has ``count`` requests in flight besides the scrape that asks (the stalled clients are inside
    the app, their bodies being read). The deadline is generous: on a loaded 2-core machine a worker can take many
    seconds to accept a connection; the wait ends as soon as the count is seen."""
    deadline = time.monotonic() + timeout
    while (seen := gauge(base, "occflownet_http_requests_in_flight") - 1) != count:
        assert time.monotonic() < deadline, f"the server never had {count} requests in flight (last seen: {seen})"
        time.sleep(0.02)


def error_of(answer: bytes) -> tuple[int, dict, dict]:
    """A raw HTTP/1.1 answer → (status, lower-cased headers, JSON body)."""
    assert answer, "no answer"
    head, _, body = answer.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), headers, json.loads(body)


def port_of(base: str) -> int:
    return int(base.rsplit(":", 1)[1])


# ---------------------------------------------------------------- stalled and slow uploads

def test_a_valid_request_is_served_while_five_uploads_stall(model_path):
    """Five clients send the headers and 1,000 bytes of a body, then nothing; the body deadline (30 s) is far
    away, so only admission after the upload lets the valid request through."""
    settings = ServeSettings(model_path=str(model_path), max_inflight=1, max_queue=4, body_timeout_s=30)
    with running_server(create_app(settings)) as base:
        wait_ready(base)
        stalled = [stalled_upload(port_of(base)) for _ in range(5)]
        try:
            wait_for_requests(base, 5)
            assert_grid(post(base))
            assert gauge(base, "occflownet_uploads_in_progress") == 5               # still stalled
            assert gauge(base, "occflownet_inference_queue_depth") == 0
        finally:
            for sock in stalled:
                sock.close()


def test_a_stalled_body_gets_408_and_its_connection_is_closed(model_path):
    settings = ServeSettings(model_path=str(model_path), body_timeout_s=0.5)
    with running_server(create_app(settings)) as base:
        wait_ready(base)
        with stalled_upload(port_of(base)) as sock:
            answer = read_answer(sock, 20)
            assert answer, "no answer to a stalled upload"
            status, headers, body = error_of(answer)
            assert (status, body["error"]["code"]) == (408, "body_timeout"), answer
            assert "0.5 s" in body["error"]["message"]
            assert headers["connection"] == "close"
            assert sock.recv(1) == b""                                    # closed by the server
        assert_grid(post(base))


def test_a_body_dripping_in_gets_408_at_its_deadline(model_path):
    """The deadline is for the whole body, not between reads: a byte every 50 ms never lets a read wait long."""
    settings = ServeSettings(model_path=str(model_path), body_timeout_s=1.0)
    with running_server(create_app(settings)) as base:
        wait_ready(base)
        with stalled_upload(port_of(base)) as sock:
            sock.setblocking(False)
            answer, stop_at = b"", time.monotonic() + 20
            while not answer and time.monotonic() < stop_at:
                try:
                    answer = sock.recv(65536)
                except BlockingIOError:
                    sock.send(b"x")
                    time.sleep(0.05)
            sock.setblocking(True)
            status, _, body = error_of(answer + read_answer(sock, 5))
            assert (status, body["error"]["code"]) == (408, "body_timeout")


def test_more_uploads_than_the_limit_get_503_busy(model_path):
    settings = ServeSettings(model_path=str(model_path), max_uploads=2, body_timeout_s=30)
    with running_server(create_app(settings)) as base:
        wait_ready(base)
        stalled = [stalled_upload(port_of(base)) for _ in range(2)]
        wait_for_requests(base, 2)
        r = post(base)
        assert r.status_code == 503 and r.json()["error"]["code"] == "busy", r.text
        assert r.headers["retry-after"] == "1" and r.headers["connection"] == "close"
        assert httpx.get(f"{base}/healthz").status_code == 200             # bodiless requests are not uploads
        for sock in stalled:
            sock.close()
        wait_for_requests(base, 0)
        assert_grid(post(base))
        samples = metric_samples(httpx.get(f"{base}/metrics").text)
        assert samples[("occflownet_rejected_total", (("reason", "uploads"),))] == 1


def test_sigterm_ends_stalled_uploads_and_finishes_the_work_in_flight(model_path, monkeypatch):
    """uvicorn in this (main) thread, as `occflownet serve` runs it: SIGTERM while one request computes (held until
    the stalled clients have their answer) and five uploads stall → the stalled ones get 503 shutting_down, the
    computing one its grid, and the server returns."""
    settings = ServeSettings(model_path=str(model_path), max_inflight=1, max_queue=4, body_timeout_s=60)
    runtime = ModelRuntime.load(model_path, settings)
    runtime.warm_up()
    computing, release = threading.Event(), threading.Event()
    real_infer = runtime.infer
    runtime.infer = lambda *a: (computing.set(), release.wait(60), real_infer(*a))[2]
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings, runtime=runtime), host="127.0.0.1", port=port,
                                           log_level="warning", timeout_graceful_shutdown=30))
    outcome = {}

    def clients():
        base = f"http://127.0.0.1:{port}"
        try:
            wait_ready(base)
            result = []
            busy = threading.Thread(target=lambda: result.append(post(base)))
            busy.start()
            assert computing.wait(30)
            stalled = [stalled_upload(port) for _ in range(5)]
            wait_for_requests(base, 6)                                      # and the one computing
            os.kill(os.getpid(), signal.SIGTERM)
            deadline = time.monotonic() + 20
            outcome["stalled"] = [read_answer(s, max(0.1, deadline - time.monotonic())) for s in stalled]
            release.set()
            busy.join(60)
            outcome["busy"] = result
        except BaseException as exc:  # noqa: BLE001 - reported by the test below
            outcome["error"] = exc
            server.should_exit = True
        finally:
            release.set()

    thread = threading.Thread(target=clients, daemon=True)
    monkeypatch.setattr(signal, "raise_signal", lambda sig: None)     # uvicorn re-raises the signal it caught
    thread.start()
    server.run()
    thread.join(60)
    assert "error" not in outcome, outcome.get("error")
    for answer in outcome["stalled"]:
        assert answer, "a stalled upload got no answer"
        status, headers, body = error_of(answer)
        assert (status, body["error"]["code"], headers["connection"]) == (503, "shutting_down", "close")
    assert len(outcome["busy"]) == 1
    assert_grid(outcome["busy"][0])


def _serve_cmd(*args) -> list[str]:
    return [sys.executable, "-m", "occflownet", "serve", *args]


@pytest.mark.parametrize("workers", [1, 2])
def test_cli_sigterm_exits_with_stalled_clients_connected(model_path, tmp_path, workers):
    port = free_port()
    env = os.environ | ({"PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "metrics")} if workers > 1 else {})
    proc = subprocess.Popen(_serve_cmd("--model", str(model_path), "--port", str(port), "--workers", str(workers),
                                       "--threads", "1", "--body-timeout", "300", "--no-access-log"),
                            env=env, cwd=REPO, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    base = f"http://127.0.0.1:{port}"
    stalled = []
    try:
        wait_ready(base, 60, proc)
        deadline = time.monotonic() + 60                    # every worker warmed up (the minimum over the workers)
        while gauge(base, "occflownet_model_ready") != 1:
            assert time.monotonic() < deadline, "the workers never all became ready"
            time.sleep(0.05)
        assert_grid(post(base))
        stalled = [stalled_upload(port) for _ in range(5)]
        wait_for_requests(base, 5)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)                                   # the target: ≤ 30 s; it takes about 1 s (the drain)
        except subprocess.TimeoutExpired:
            pytest.fail("occflownet serve did not exit within 30 s of SIGTERM with stalled clients")
        answers = [error_of(read_answer(s, 5)) for s in stalled]
        assert {(status, body["error"]["code"]) for status, _, body in answers} == {(503, "shutting_down")}
    finally:
        for sock in stalled:
            sock.close()
        stop_server(proc)


# ---------------------------------------------------------------- processes

def _children(pid: int) -> list[int]:
    """The worker processes uvicorn spawned under ``pid`` (multiprocessing's spawn_main; not its resource
    tracker)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == pid and b"spawn_main" in cmdline:
            found.append(int(entry.name))
    return found


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.parametrize("when", ["serving", "starting"])
def test_kill_9_of_the_supervisor_stops_its_workers(model_path, tmp_path, when):
    """``kill -9`` of the supervisor of two workers, once they serve, or as soon as both processes exist (a worker
    may still be loading its model then): the workers shut down by themselves and the port closes."""
    port = free_port()
    env = os.environ | {"PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "metrics")}
    proc = subprocess.Popen(_serve_cmd("--model", str(model_path), "--port", str(port), "--workers", "2",
                                       "--threads", "1", "--no-access-log"),
                            env=env, cwd=REPO, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    workers = []
    try:
        if when == "serving":
            wait_ready(f"http://127.0.0.1:{port}", 60, proc)
        deadline = time.monotonic() + 30
        while len(workers := _children(proc.pid)) < 2:
            assert time.monotonic() < deadline, f"workers not found: {workers}"
            time.sleep(0.1)
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 30                     # they notice within 0.5 s and drain for 1 s
        while any(_running(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_running(pid) for pid in workers), "the workers outlived their supervisor"
        with pytest.raises(httpx.ConnectError):
            httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5)
    finally:
        for pid in workers:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
        stop_server(proc)


def _without_file_permission_override() -> None:
    """preexec_fn for root: drop CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH from the bounding set, so the command run
    next is held to file modes like any user (root's capabilities after exec come from that set)."""
    libc = ctypes.CDLL(None, use_errno=True)
    for capability in (1, 2):                               # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
        if libc.prctl(24, capability, 0, 0, 0) != 0:        # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def _run_held_to_file_modes(cmd: list[str], probe: Path) -> subprocess.CompletedProcess:
    """Run ``cmd`` as a user bound by file modes (this user, or root without its override capabilities); skip
    when ``probe`` (made unreadable by the caller) can still be read that way."""
    preexec = _without_file_permission_override if os.geteuid() == 0 else None
    check = subprocess.run([sys.executable, "-c", f"open({str(probe)!r}, 'rb')"], capture_output=True,
                           preexec_fn=preexec)
    if check.returncode == 0:
        pytest.skip("file modes do not bind this user here (cannot drop CAP_DAC_OVERRIDE)")
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, preexec_fn=preexec, cwd=REPO)


@pytest.mark.parametrize("unreadable", ["file", "folder"])
def test_an_unreadable_model_is_named_permission_denied(model_path, tmp_path, unreadable):
    folder = tmp_path / "models"
    folder.mkdir()
    model = folder / "model.onnx"
    model.write_bytes(model_path.read_bytes())
    target = model if unreadable == "file" else folder
    target.chmod(0)
    try:
        proc = _run_held_to_file_modes(_serve_cmd("--model", str(model), "--port", str(free_port())), model)
    finally:
        target.chmod(stat.S_IRWXU)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == f"occflownet serve: cannot read model {model}: permission denied", proc.stderr


def test_a_port_outside_the_range_is_one_line(model_path):
    proc = subprocess.run(_serve_cmd("--model", str(model_path), "--port", "99999"), capture_output=True, text=True,
                          timeout=60, cwd=REPO)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == ["occflownet serve: cannot listen on 127.0.0.1:99999: port 99999 is outside "
                                        "0..65535"]


def test_a_port_in_use_is_one_line(model_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for workers in ("1", "2"):
            proc = subprocess.run(_serve_cmd("--model", str(model_path), "--port", str(port), "--workers", workers),
                                  capture_output=True, text=True, timeout=60, cwd=REPO)
            assert proc.returncode == 2
            assert proc.stderr.splitlines() == [f"occflownet serve: cannot listen on 127.0.0.1:{port}: Address "
                                                "already in use"]


@pytest.mark.parametrize("provider, why", [("CUDAExecutionProvider", "not in this onnxruntime build"),
                                           ("CPUExecutionProviderX", "unknown name")])
def test_a_provider_onnxruntime_lacks_stops_start_up(model_path, provider, why):
    import onnxruntime as ort

    if provider in ort.get_available_providers():
        pytest.skip(f"{provider} is available here")
    env = os.environ | {"OCCFLOWNET_PROVIDERS": provider}
    proc = subprocess.run(_serve_cmd("--model", str(model_path), "--port", str(free_port())), capture_output=True,
                          text=True, timeout=30, cwd=REPO, env=env)
    assert proc.returncode == 2
    available = ", ".join(ort.get_available_providers())
    assert proc.stderr.splitlines() == [f"occflownet serve: OCCFLOWNET_PROVIDERS / --providers: {provider} ({why}); "
                                        f"available here: {available}"]


# ---------------------------------------------------------------- answers

class _Records(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records = []

    def emit(self, record):
        self.records.append(record)


def test_an_unhandled_error_is_logged_once_and_answered_500(model_path):
    settings = ServeSettings(model_path=str(model_path), warmup=False)
    runtime = ModelRuntime.load(model_path, settings)

    def broken(*_):
        raise RuntimeError("boom")

    runtime.infer = broken
    records = _Records()
    loggers = [logging.getLogger(name) for name in ("uvicorn", "uvicorn.error", "occflownet.serve", "")]
    with running_server(create_app(settings, runtime=runtime)) as base:
        for logger in loggers:
            logger.addHandler(records)
        try:
            r = post(base)
            assert httpx.get(f"{base}/healthz").status_code == 200
        finally:
            for logger in loggers:
                logger.removeHandler(records)
    assert r.status_code == 500 and r.json() == {"error": {"code": "internal", "message": "internal error: "
                                                                                           "RuntimeError"}}
    tracebacks = {id(rec): rec for rec in records.records if rec.exc_info}
    assert len(tracebacks) == 1, [rec.getMessage() for rec in tracebacks.values()]


def test_a_calibration_that_breaks_its_parser_is_400(model_path, monkeypatch):
    import occflownet.serve.calibration as calibration

    with TestClient(create_app(ServeSettings(model_path=str(model_path), warmup=False))) as c:
        deep = "[" * 2000 + "]" * 2000                     # Python's JSON parser recurses: RecursionError
        r = c.post("/v1/occupancy", files=image_files(IMAGES) | {"calibration": (None, deep)})
        assert r.status_code == 400 and r.json()["error"]["code"] == "bad_calibration", r.text
        for error in (RecursionError("maximum recursion depth exceeded"), TypeError("unforeseen")):
            def parse(*_a, error=error, **_k):
                raise error
            monkeypatch.setattr(calibration, "frame_calibration", parse)
            calib = json.dumps(default_rig(96, 54))
            r = c.post("/v1/occupancy", files=image_files(IMAGES) | {"calibration": (None, calib)})
            assert r.status_code == 400, r.text
            assert r.json()["error"] == {"code": "bad_calibration", "message": "calibration part cannot be used: "
                                         f"{type(error).__name__}: {error}"}
        monkeypatch.undo()
        assert c.post("/v1/occupancy", files=image_files(IMAGES)).status_code == 200


def test_every_answer_says_nosniff(model_path):
    settings = ServeSettings(model_path=str(model_path), warmup=False, max_body_bytes=10_000_000)
    with TestClient(create_app(settings)) as c:
        answers = {
            "json": c.post("/v1/occupancy", files=image_files(IMAGES)),
            "octet": c.post("/v1/occupancy", files=image_files(IMAGES), headers=OCTET),
            "png": c.post("/v1/occupancy", files=image_files(IMAGES), headers={"Accept": "image/png"}),
            "metrics": c.get("/metrics"), "metadata": c.get("/v1/metadata"), "openapi": c.get("/openapi.json"),
            "ui": c.get("/ui"), "404": c.get("/nowhere"), "405": c.delete("/v1/occupancy"),
            "413": c.post("/v1/occupancy", content=b"x" * 10_000_001),
            "422": c.post("/v1/occupancy", files={"CAM_FRONT": ("a.png", b"x", "image/png")}),
        }
    with TestClient(create_app(settings.model_copy(update={"api_key": "k"}))) as c:
        answers["401"] = c.get("/v1/metadata")
    assert {name: r.headers.get("x-content-type-options") for name, r in answers.items()} == \
        {name: "nosniff" for name in answers}
    assert {name: r.status_code for name, r in answers.items() if name.isdigit()} == \
        {"401": 401, "404": 404, "405": 405, "413": 413, "422": 422}


def test_api_docs_are_off_unless_asked_for(model_path):
    settings = ServeSettings(model_path=str(model_path), warmup=False)
    with TestClient(create_app(settings)) as c:
        assert c.get("/docs").status_code == 404 and c.get("/redoc").status_code == 404
        assert c.get("/openapi.json").json()["paths"]["/v1/occupancy"]
    with TestClient(create_app(settings.model_copy(update={"docs": True}))) as c:
        assert "swagger-ui" in c.get("/docs").text and "redoc" in c.get("/redoc").text
