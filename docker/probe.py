"""Probe a running occflownet serving container (run by scripts/docker-check with the project's venv python).

    python docker/probe.py --url http://127.0.0.1:PORT --frame DIR --reference grid.npz --model m.onnx \
        --started-at EPOCH_SECONDS

Checks: /healthz answers ok and /readyz becomes ready, each polled every 50 ms by
``occflownet.serve.client.wait_ready`` (prints the seconds since --started-at, i.e. since `docker run` returned, and
the server's own warm-up time); /v1/metadata names the model file; then one
POST /v1/occupancy of the frame per response format, each grid equal, voxel for voxel, to the reference computed by
local onnxruntime (`occflownet predict --model`). The PNG is decoded and compared pixel for pixel with the picture
serve/encode.py draws from the reference grid with the model's class colours. Last, the browser page ``/ui`` and its
script, byte for byte the package's (tests/test_serve_page.py drives the page itself in Chromium). Exit status 1 on the first failure.
"""
from __future__ import annotations

import argparse
import base64
import io
import json
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from occflownet.serve.client import ServerNotReady, wait_ready

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
SHAPE = (200, 200, 16)


class ProbeError(RuntimeError):
    pass


def check(condition: bool, message: str) -> None:
    if not condition:
        raise ProbeError(message)


def expected_png(reference: np.ndarray, model: Path) -> np.ndarray:
    """The top-down picture serve/encode.py draws, from the reference grid and the model's own metadata."""
    import onnxruntime as ort

    from occflownet.pictures import top_down

    meta = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"]).get_modelmeta()
    props = meta.custom_metadata_map
    colors = np.asarray(json.loads(props["class_colors"]), dtype=np.uint8)
    return top_down(reference, colors, int(json.loads(props["free_index"])))


def post(client: httpx.Client, frame: Path, accept: str) -> httpx.Response:
    files = {c: (f"{c}.jpg", (frame / f"{c}.jpg").read_bytes(), "image/jpeg") for c in CAMERAS}
    files["calibration"] = ("calib.json", (frame / "calib.json").read_bytes(), "application/json")
    r = client.post("/v1/occupancy", files=files, headers={"Accept": accept}, timeout=120)
    check(r.status_code == 200, f"POST Accept {accept}: {r.status_code} {r.text[:300]}")
    got = r.headers.get("content-type", "").split(";")[0]
    check(got == accept, f"POST Accept {accept}: answered Content-Type {got!r}")
    return r


def decode_grid(accept: str, r: httpx.Response) -> np.ndarray:
    if accept == "application/json":
        body = r.json()
        check(body["shape"] == list(SHAPE) and body["dtype"] == "uint8", f"JSON shape/dtype {body['shape']} "
              f"{body['dtype']}")
        return np.frombuffer(base64.b64decode(body["occupancy_base64"]), np.uint8).reshape(SHAPE)
    check(r.headers.get("x-occupancy-shape") == "200,200,16", f"{accept}: X-Occupancy-Shape "
          f"{r.headers.get('x-occupancy-shape')!r}")
    if accept == "application/octet-stream":
        check(len(r.content) == int(np.prod(SHAPE)), f"octet-stream body is {len(r.content)} bytes")
        return np.frombuffer(r.content, np.uint8).reshape(SHAPE)
    if accept == "application/x-npy":
        grid = np.load(io.BytesIO(r.content), allow_pickle=False)
        check(grid.dtype == np.uint8 and grid.shape == SHAPE, f"npy {grid.dtype} {grid.shape}")
        return grid
    raise AssertionError(accept)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--frame", required=True, type=Path)
    ap.add_argument("--reference", required=True, type=Path, help="npz written by `occflownet predict`")
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--started-at", required=True, type=float)
    ap.add_argument("--ready-timeout", type=float, default=120)
    args = ap.parse_args()

    reference = np.load(args.reference)["occupancy"]
    check(reference.shape == SHAPE and reference.dtype == np.uint8, f"reference {reference.shape} {reference.dtype}")
    occupied = int((reference != 17).sum())
    print(f"probe: reference grid from local onnxruntime: {occupied} occupied voxels")
    if occupied == 0:
        print("probe: warning: the reference grid is all free, so the comparison below is weak", file=sys.stderr)

    with httpx.Client(base_url=args.url) as client:
        health = wait_ready(args.url, args.ready_timeout, path="/healthz")
        check(health.get("status") == "ok", f"/healthz: {health}")
        print(f"probe: /healthz ok {time.time() - args.started_at:.2f} s after `docker run` returned")
        ready = wait_ready(args.url, args.ready_timeout)
        check(ready.get("status") == "ready", f"/readyz: {ready}")
        print(f"probe: /readyz ready {time.time() - args.started_at:.2f} s after `docker run` returned "
              f"(server warm-up {ready.get('warmup_seconds')} s)")
        meta = client.get("/v1/metadata", timeout=10)
        check(meta.status_code == 200, f"/v1/metadata: {meta.status_code}")
        text = json.dumps(meta.json())
        check(args.model.name in text, f"/v1/metadata does not name {args.model.name}")

        for accept in ("application/json", "application/octet-stream", "application/x-npy"):
            t0 = time.perf_counter()
            grid = decode_grid(accept, post(client, args.frame, accept))
            diff = int((grid != reference).sum())
            check(diff == 0, f"{accept}: {diff} voxels differ from local onnxruntime")
            print(f"probe: POST {accept}: grid equal to local onnxruntime ({(time.perf_counter() - t0) * 1e3:.0f} ms)")

        import cv2

        r = post(client, args.frame, "image/png")
        check(r.content[:8] == b"\x89PNG\r\n\x1a\n", "image/png: body is not a PNG")
        bgr = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
        check(bgr is not None, "image/png: cannot decode")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        want = expected_png(reference, args.model)
        check(rgb.shape == want.shape, f"image/png: {rgb.shape[1]}x{rgb.shape[0]}, expected "
              f"{want.shape[1]}x{want.shape[0]}")
        diff = int((rgb != want).any(axis=2).sum())
        check(diff == 0, f"image/png: {diff} pixels differ from the picture drawn from the local grid")
        print(f"probe: POST image/png: {rgb.shape[1]}x{rgb.shape[0]}, equal to the picture of the local grid")
        check_ui(client)
    return 0


def check_ui(client: httpx.Client) -> None:
    """The browser page and its one script come from the image's package data, with the page's strict policy."""
    from occflownet.viewer import BUNDLE, PAGE

    page = client.get("/ui", timeout=10)
    check(page.status_code == 200 and page.content == PAGE.read_bytes(), f"GET /ui: {page.status_code}")
    check("default-src 'none'" in page.headers.get("content-security-policy", ""), "GET /ui: no strict policy")
    script = client.get("/ui/occflownet-web.js", timeout=10)
    check(script.status_code == 200 and script.content == BUNDLE.read_bytes(),
          f"GET /ui/occflownet-web.js: {script.status_code}, {len(script.content)} bytes, not the package's script")
    print(f"probe: GET /ui and its script ({len(script.content) / 1024:.0f} KiB) served from the image's package data")


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ProbeError, ServerNotReady) as exc:
        print(f"probe: FAILED: {exc}", file=sys.stderr)
        sys.exit(1)
