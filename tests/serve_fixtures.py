"""Test helpers for serve/: a small fake model that follows ONNX contract v1 exactly, its numpy reference, images.

The fake model's outputs depend on every input, and on which image is which camera's, so the tests can tell whether
the server fed the right tensors in the right order:
    m   = mean of all image bytes                       (per batch item)
    r_k = mean of the bytes of camera k's top image row (k = 0..5 in the model's camera order; a sum of at most
          2^24 / 255 integers is exact in float32 whatever the order, so floor(r_k) is the same on every CPU)
    u   = fx of CAM_FRONT / image width                 (scale-invariant: unchanged by consistent resizing)
    tx  = x translation of CAM_FRONT's cam2ego
    z   = ramp + 4 (m/255 - 0.5) + 8 (u - u0) + (tx - tx0),  ramp = P/4 - 2 with a fixed uint8 pattern P in [0, 16]
    density   = sigmoid(z)                              float32 [B, 200, 200, 16]
    occupancy = (floor(r_k) + P) mod 17 where density >= threshold else 17   uint8 [B, 200, 200, 16], where
                k = camera_slab(x) = x * 6 // 200: camera k's image decides the classes of the k-th sixth of the
                grid along x (:func:`camera_slab`), so images swapped between cameras swap classes between slabs.
u0 and tx0 come from the default calibration, so black images with it give density = sigmoid(ramp - 2).
"""
from __future__ import annotations

import io
import json
import socket
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from occflownet import __version__
from occflownet.occ3d import CAMERAS, CLASS_COLORS, CLASS_NAMES, FREE, GRID
from occflownet.rig import default_rig
from occflownet.serve.client import wait_ready

SHARED = Path(__file__).resolve().parents[2] / "shared"
FRAME_DIR = SHARED / "data" / "nuscenes-frame"
DEFAULT_SIZE = (480, 270)  # (w, h) of the fake model's default calibration


def fake_pattern(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 17, size=GRID.shape, dtype=np.uint8)


def camera_slab(x: np.ndarray | int) -> np.ndarray | int:
    """The camera (index in the model's camera order) whose image decides the fake model's classes at grid index
    ``x``: the six equal-as-can-be slabs of x, 0..199 → 0..5."""
    return np.asarray(x) * 6 // GRID.shape[0]


def _camera_of_voxel() -> np.ndarray:
    """int64 [200, 200, 16]: :func:`camera_slab` of each voxel's x."""
    return np.broadcast_to(camera_slab(np.arange(GRID.shape[0]))[:, None, None], GRID.shape).astype(np.int64)


def fake_metadata(threshold: float = 0.5, default_size=DEFAULT_SIZE) -> dict:
    """Contract-v1 metadata (values not yet JSON-encoded)."""
    return {
        "classes": list(CLASS_NAMES), "free_index": FREE, "grid": GRID.to_dict(), "cameras": list(CAMERAS),
        "class_colors": CLASS_COLORS.tolist(), "threshold": threshold, "input_size": [128, 352], "preset": "fake",
        "default_calibration": default_rig(*default_size), "occflownet_version": __version__, "onnx_contract": "v1",
    }


def build_fake_model(path: Path, threshold: float = 0.5, seed: int = 0, default_size=DEFAULT_SIZE,
                     metadata: dict | None = None, fixed_hw: tuple[int, int] | None = None) -> Path:
    """Write the fake contract-v1 model to ``path`` (about 0.7 MB); ``metadata`` overrides/extends the keys;
    ``fixed_hw`` pins the images input's H and W (contract v1 leaves them dynamic)."""
    import onnx
    from onnx import TensorProto, helper

    X, Y, Z = GRID.shape
    graph = helper.make_graph(
        _fake_nodes(), "occflownet_fake",
        [helper.make_tensor_value_info("images", TensorProto.UINT8, ["B", 6, *(fixed_hw or ("H", "W")), 3]),
         helper.make_tensor_value_info("intrinsics", TensorProto.FLOAT, ["B", 6, 3, 3]),
         helper.make_tensor_value_info("cam2ego", TensorProto.FLOAT, ["B", 6, 4, 4])],
        [helper.make_tensor_value_info("occupancy", TensorProto.UINT8, ["B", X, Y, Z]),
         helper.make_tensor_value_info("density", TensorProto.FLOAT, ["B", X, Y, Z])],
        initializer=_fake_initializers(threshold, seed, default_size))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="occflownet-tests")
    model.ir_version = 8
    meta = fake_metadata(threshold, default_size) | (metadata or {})
    helper.set_model_props(model, {k: json.dumps(v) for k, v in meta.items()})
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path


def _fake_initializers(threshold: float, seed: int, default_size) -> list:
    """The fake graph's constants: the pattern P uint8 [200, 200, 16], u0 and tx0 of the default calibration, τ."""
    from onnx import numpy_helper

    calib = default_rig(*default_size)
    front = calib["cameras"][CAMERAS[0]]
    u0 = front["intrinsic"][0][0] / default_size[0]
    tx0 = front["cam2ego"][0][3]

    def const(name, value):
        return numpy_helper.from_array(np.asarray(value), name)

    return [
        const("P", fake_pattern(seed)), const("quarter", np.float32(0.25)),
        const("two", np.float32(2.0)), const("four", np.float32(4.0)), const("eight", np.float32(8.0)),
        const("half", np.float32(0.5)), const("inv255", np.float32(1 / 255)), const("u0", np.float32(u0)),
        const("tx0", np.float32(tx0)), const("tau", np.float32(threshold)), const("seventeen", np.int64(17)),
        const("free", np.uint8(FREE)), const("axes123", np.array([1, 2, 3], np.int64)),
        const("i0", np.array(0, np.int64)), const("i3", np.array(3, np.int64)),
        const("C", _camera_of_voxel()), const("row0", np.array([0], np.int64)), const("row1", np.array([1], np.int64)),
        const("axis2", np.array([2], np.int64)),
    ]


def _fake_nodes() -> list:
    """The fake graph's nodes (module docstring): images [B, 6, H, W, 3], intrinsics [B, 6, 3, 3], cam2ego
    [B, 6, 4, 4] → occupancy uint8 and density float32 [B, 200, 200, 16]."""
    from onnx import TensorProto, helper

    n = helper.make_node
    return [
        n("Cast", ["images"], ["img_f"], to=TensorProto.FLOAT),
        n("ReduceMean", ["img_f"], ["m"], axes=[1, 2, 3, 4], keepdims=0),           # [B]
        n("Shape", ["images"], ["shape"]),
        n("Gather", ["shape", "i3"], ["w_i"], axis=0),
        n("Cast", ["w_i"], ["w_f"], to=TensorProto.FLOAT),
        n("Gather", ["intrinsics", "i0"], ["k_front"], axis=1),                     # [B,3,3]
        n("Gather", ["k_front", "i0"], ["k_row0"], axis=1),                         # [B,3]
        n("Gather", ["k_row0", "i0"], ["fx"], axis=1),                              # [B]
        n("Div", ["fx", "w_f"], ["u"]),
        n("Sub", ["u", "u0"], ["du"]),
        n("Mul", ["du", "eight"], ["du8"]),
        n("Gather", ["cam2ego", "i0"], ["t_front"], axis=1),                        # [B,4,4]
        n("Gather", ["t_front", "i0"], ["t_row0"], axis=1),                         # [B,4]
        n("Gather", ["t_row0", "i3"], ["tx"], axis=1),                              # [B]
        n("Sub", ["tx", "tx0"], ["dtx"]),
        n("Mul", ["m", "inv255"], ["m01"]),
        n("Sub", ["m01", "half"], ["mc"]),
        n("Mul", ["mc", "four"], ["m4c"]),
        n("Add", ["m4c", "du8"], ["s1"]),
        n("Add", ["s1", "dtx"], ["shift"]),                                         # [B]
        n("Unsqueeze", ["shift", "axes123"], ["shift4"]),
        n("Cast", ["P"], ["P_f"], to=TensorProto.FLOAT),
        n("Mul", ["P_f", "quarter"], ["Pq"]),
        n("Sub", ["Pq", "two"], ["ramp"]),                                          # [200,200,16]
        n("Add", ["ramp", "shift4"], ["z"]),                                        # [B,200,200,16]
        n("Sigmoid", ["z"], ["density"]),
        n("Slice", ["img_f", "row0", "row1", "axis2"], ["top"]),                   # [B,6,1,W,3]
        n("ReduceMean", ["top"], ["r"], axes=[2, 3, 4], keepdims=0),                # [B,6]
        n("Floor", ["r"], ["r_floor"]),
        n("Cast", ["r_floor"], ["r_int"], to=TensorProto.INT64),
        n("Gather", ["r_int", "C"], ["r_voxel"], axis=1),                           # [B,200,200,16]
        n("Cast", ["P"], ["P64"], to=TensorProto.INT64),
        n("Add", ["P64", "r_voxel"], ["sem_raw"]),
        n("Mod", ["sem_raw", "seventeen"], ["sem64"]),
        n("Cast", ["sem64"], ["sem"], to=TensorProto.UINT8),
        n("GreaterOrEqual", ["density", "tau"], ["occupied"]),
        n("Where", ["occupied", "sem", "free"], ["occupancy"]),
    ]


def fake_reference(images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray, threshold: float = 0.5,
                   seed: int = 0, default_size=DEFAULT_SIZE) -> np.ndarray:
    """numpy twin of the fake model for one frame: images uint8 [6, H, W, 3], intrinsics [6, 3, 3] for H×W,
    cam2ego [6, 4, 4] → occupancy uint8 [200, 200, 16]."""
    calib = default_rig(*default_size)
    front = calib["cameras"][CAMERAS[0]]
    u0 = np.float32(front["intrinsic"][0][0] / default_size[0])
    tx0 = np.float32(front["cam2ego"][0][3])
    P = fake_pattern(seed)
    m = np.float32(images.astype(np.float32).mean(dtype=np.float64))
    r = np.floor(images[:, 0].astype(np.float64).mean(axis=(1, 2))).astype(np.int64)      # [6]: top rows
    u = np.float32(intrinsics[0, 0, 0]) / np.float32(images.shape[2])
    shift = (m * np.float32(1 / 255) - np.float32(0.5)) * 4 + (u - u0) * 8 + (np.float32(cam2ego[0, 0, 3]) - tx0)
    z = P.astype(np.float32) * np.float32(0.25) - 2 + np.float32(shift)
    density = 1 / (1 + np.exp(-z.astype(np.float64)))
    sem = ((P.astype(np.int64) + r[_camera_of_voxel()]) % 17).astype(np.uint8)
    return np.where(density >= threshold, sem, FREE).astype(np.uint8)


def synthetic_images(size=(96, 54), seed: int = 0) -> list[np.ndarray]:
    """Six RGB uint8 [h, w, 3] images with smooth gradients plus noise (compress well, decode exactly as PNG)."""
    w, h = size
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    out = []
    for i in range(6):
        base = np.stack([(xx * 255 // max(1, w - 1)), (yy * 255 // max(1, h - 1)), np.full_like(xx, 40 * i)], -1)
        out.append(np.clip(base + rng.integers(0, 20, size=base.shape), 0, 255).astype(np.uint8))
    return out


def encode_image(rgb: np.ndarray, fmt: str = ".png", quality: int = 90) -> bytes:
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == ".jpg" else []
    ok, buf = cv2.imencode(fmt, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    assert ok
    return buf.tobytes()


def image_files(images: list[np.ndarray], fmt: str = ".png") -> dict:
    """httpx/TestClient ``files=`` mapping: one part per camera, in camera order."""
    mime = "image/png" if fmt == ".png" else "image/jpeg"
    return {cam: (f"{cam}{fmt}", encode_image(im, fmt), mime) for cam, im in zip(CAMERAS, images)}


def real_frame_files() -> tuple[dict, bytes]:
    """The shared real frame as ``files=`` (six JPEGs) and its calib.json bytes."""
    files = {cam: (f"{cam}.jpg", (FRAME_DIR / f"{cam}.jpg").read_bytes(), "image/jpeg") for cam in CAMERAS}
    return files, (FRAME_DIR / "calib.json").read_bytes()


def frame_request_files(cameras=CAMERAS) -> dict:
    """The shared real frame's JPEGs of ``cameras`` and its calib.json as ``files=`` of ``POST /v1/occupancy``."""
    files = {c: (f"{c}.jpg", (FRAME_DIR / f"{c}.jpg").read_bytes(), "image/jpeg") for c in cameras}
    files["calibration"] = ("calib.json", (FRAME_DIR / "calib.json").read_bytes(), "application/json")
    return files


def post_frame(server: str, accept: str = "application/json", cameras=CAMERAS):
    """``POST /v1/occupancy`` of the real frame (httpx, JSON answers parsed) → (response, round trip in ms)."""
    import time

    import httpx

    t0 = time.perf_counter()
    r = httpx.post(f"{server}/v1/occupancy", files=frame_request_files(cameras), headers={"Accept": accept},
                   timeout=60)
    if accept == "application/json" and r.status_code == 200:
        r.json()
    return r, (time.perf_counter() - t0) * 1e3


def send_from_page(page, cameras=CAMERAS, calibration: bool = True) -> dict:
    """In the server page (a selenium driver on ``/ui``): choose the real frame's images (and calib.json), press
    the button, wait for the outcome → the page's ``occPage.last`` (ok, status, timings, ...)."""
    from selenium.webdriver.common.by import By

    try:
        from browser import wait_for               # the tests: tests/ is on the path
    except ModuleNotFoundError:
        from tests.browser import wait_for         # the benchmarks: imported as tests.serve_fixtures

    page.execute_script("window.occPage.last = null; document.getElementById('images').value = '';")
    page.find_element(By.ID, "images").send_keys("\n".join(str(FRAME_DIR / f"{c}.jpg") for c in cameras))
    if calibration:
        page.find_element(By.ID, "calibration").send_keys(str(FRAME_DIR / "calib.json"))
    page.find_element(By.ID, "run").click()
    return wait_for(page, "window.occPage.last", timeout=120)


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def wait_app_ready(client, timeout: float = 10.0) -> dict:
    """:func:`occflownet.serve.client.wait_ready` for an in-process app (a starlette TestClient) → /readyz JSON."""
    def get(path: str) -> tuple[int, bytes]:
        r = client.get(path)
        return r.status_code, r.content

    return wait_ready("", timeout, get=get, interval=0.01)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def running_server(app, **config):
    """uvicorn serving ``app`` in a thread on a free 127.0.0.1 port (``config``: more uvicorn.Config arguments)
    → base URL; stopped on exit."""
    import threading
    import time

    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", **config))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.01)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


def stalled_upload(port: int, sent: int = 1000, declared: int = 1_000_000) -> socket.socket:
    """A client that stalls: a connection to 127.0.0.1:``port`` that sends the headers of a ``POST /v1/occupancy``
    declaring a body of ``declared`` bytes, then ``sent`` bytes of it, then nothing. The caller closes it."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(b"POST /v1/occupancy HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                 b"Content-Length: %d\r\n\r\n" % declared + b"--b\r\n" + b"x" * max(0, sent - 5))
    return sock


def read_answer(sock: socket.socket, timeout: float) -> bytes:
    """What the server sends on ``sock`` until it closes the connection or ``timeout`` seconds pass (b"" if it
    sent nothing)."""
    import time

    deadline = time.monotonic() + timeout
    answer = b""
    while time.monotonic() < deadline:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data = sock.recv(65536)
        except socket.timeout:
            break
        except ConnectionResetError:
            break
        if not data:
            break
        answer += data
    return answer


def stop_server(proc, timeout: float = 20.0) -> None:
    """SIGTERM a server subprocess, SIGKILL it if it does not exit within ``timeout`` seconds."""
    import subprocess

    proc.terminate()
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def metric_samples(text: str) -> dict[tuple, float]:
    """Prometheus exposition text → {(sample name, ((label, value), ...) sorted): value} (prometheus_client's own
    parser, so the text is checked to be valid exposition)."""
    from prometheus_client.parser import text_string_to_metric_families

    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}
