"""Integration: a real random-init ``tiny`` export (``occflownet export``) served over HTTP with the real frame.

The server's answer must equal a plain onnxruntime run of the same file on the same frame, decoded and calibrated
here independently of serve/ (cv2 RGB decode, occflownet.contract.calibration_arrays).
"""
import io
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from serve_fixtures import FRAME_DIR, real_frame_files
from starlette.testclient import TestClient

from occflownet.occ3d import CAMERAS
from occflownet.contract import calibration_arrays

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    if not (REPO / "export" / "onnx_export.py").is_file():
        pytest.skip("export/onnx_export.py has not landed yet: no real model to serve")
    if not FRAME_DIR.is_dir():
        pytest.skip(f"shared real frame not found at {FRAME_DIR}")
    out = tmp_path_factory.mktemp("serve-export") / "tiny.onnx"
    proc = subprocess.run([sys.executable, "-m", "occflownet", "export", "--preset", "tiny", "--random-init",
                           "--seed", "0", "--out", str(out)], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert proc.returncode == 0 and out.is_file(), f"export failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return out


def _direct_inputs():
    """The frame as the contract says a tiny model is fed (JPEGs at quarter scale by DCT scaling, intrinsics by the
    pixel-centre rule with s = 1/4), made here with cv2 and numpy alone."""
    images = np.stack([cv2.cvtColor(cv2.imread(str(FRAME_DIR / f"{cam}.jpg"), cv2.IMREAD_REDUCED_COLOR_4),
                                    cv2.COLOR_BGR2RGB) for cam in CAMERAS])
    assert images.shape == (6, 225, 400, 3)
    K, T = calibration_arrays(json.loads((FRAME_DIR / "calib.json").read_text()))
    K = K.astype(np.float64)
    K[:, :2, :] *= 0.25
    K[:, :2, 2] -= 0.375                                  # (c + 0.5) / 4 - 0.5
    return images, K.astype(np.float32), T


def _direct(model: Path, images, K, T) -> tuple[np.ndarray, np.ndarray]:
    import onnxruntime as ort

    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    occ, density = session.run(["occupancy", "density"], {"images": images[None], "intrinsics": K[None],
                                                          "cam2ego": T[None]})
    assert density.shape == occ.shape and density.dtype == np.float32
    return occ[0], density[0]


def test_real_export_served_over_http_matches_a_direct_run(tiny_model):
    from occflownet.serve.app import create_app
    from occflownet.serve.model_runtime import ModelRuntime
    from occflownet.serve.settings import ServeSettings

    images, K, T = _direct_inputs()
    expected, _ = _direct(tiny_model, images, K, T)
    assert expected.shape == (200, 200, 16) and expected.dtype == np.uint8 and expected.max() <= 17
    settings = ServeSettings(model_path=str(tiny_model))
    runtime = ModelRuntime.load(tiny_model, settings)
    fed = []
    real_infer = runtime.infer
    runtime.infer = lambda *args: (fed.append(args), real_infer(*args))[1]   # record what the server feeds ORT
    with TestClient(create_app(settings, runtime=runtime)) as client:
        deadline = time.monotonic() + 120
        while client.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline, client.get("/readyz").text
            time.sleep(0.1)
        md = client.get("/v1/metadata").json()
        assert md["model"]["onnx_contract"] == "v1" and md["model"]["preset"] == "tiny"
        assert md["cameras"] == list(CAMERAS) and md["free_index"] == 17 and md["grid"]["shape"] == [200, 200, 16]
        files, calib = real_frame_files()
        fed.clear()
        r = client.post("/v1/occupancy", files=files | {"calibration": (None, calib)},
                        headers={"Accept": "application/x-npy"})
        assert r.status_code == 200, r.text
        np.testing.assert_array_equal(np.load(io.BytesIO(r.content)), expected)
        # a random-init model may predict one class everywhere, so also check the tensors themselves
        (inputs,), = fed
        got_images, got_K, got_T = inputs.images[0], inputs.intrinsics[0], inputs.cam2ego[0]
        np.testing.assert_array_equal(got_images, images)
        np.testing.assert_allclose(got_K, K, rtol=1e-6)
        np.testing.assert_allclose(got_T, T, rtol=1e-6)
        # without a calibration part the model's default calibration is used (scaled when the aspect agrees)
        r = client.post("/v1/occupancy", files=files)
        w, h = md["default_calibration"]["image_size"]
        if abs((1600 / 900) / (w / h) - 1) <= 0.01:
            assert r.status_code == 200, r.text
            assert r.json()["shape"] == [200, 200, 16]
        else:
            assert r.status_code == 400 and "calibration" in r.json()["error"]["message"]


def _serve_folder(client, folder: Path, calib: bytes) -> np.ndarray:
    files = {}
    for cam in CAMERAS:
        image = next(folder / f"{cam}{suffix}" for suffix in (".png", ".jpg") if (folder / f"{cam}{suffix}").is_file())
        files[cam] = (image.name, image.read_bytes(), "image/png" if image.suffix == ".png" else "image/jpeg")
    r = client.post("/v1/occupancy", files=files | {"calibration": (None, calib)},
                    headers={"Accept": "application/x-npy"})
    assert r.status_code == 200, r.text
    return np.load(io.BytesIO(r.content))


@pytest.mark.skipif(not FRAME_DIR.is_dir(), reason=f"shared real frame not found at {FRAME_DIR}")
def test_predict_and_http_give_identical_grids_for_the_frame_and_its_quarter_size_copy(tmp_path):
    """One calibration rule everywhere: the real frame at 1600x900 (JPEGs decoded at quarter scale)
    and resized to 400x225 (PNG, decoded whole; calib.json still says 1600x900), through `occflownet predict
    --model` and through POST /v1/occupancy, gives identical grids; both fed the pixel-centre-rescaled
    intrinsics."""
    from exported_models import exported_trained_tiny
    from occflownet.cli import main
    from occflownet.contract import calibration_arrays
    from occflownet.serve.app import create_app
    from occflownet.serve.model_runtime import ModelRuntime
    from occflownet.serve.settings import ServeSettings

    model = exported_trained_tiny()[0]
    quarter = tmp_path / "quarter"
    quarter.mkdir()
    for cam in CAMERAS:
        image = cv2.imread(str(FRAME_DIR / f"{cam}.jpg"))
        cv2.imwrite(str(quarter / f"{cam}.png"), cv2.resize(image, (400, 225), interpolation=cv2.INTER_AREA))
    calib_bytes = (FRAME_DIR / "calib.json").read_bytes()
    calib = json.loads(calib_bytes)
    assert calib["image_size"] == [1600, 900]
    settings = ServeSettings(model_path=str(model))
    runtime = ModelRuntime.load(model, settings)
    fed = []
    real_infer = runtime.infer
    runtime.infer = lambda *args: (fed.append(args), real_infer(*args))[1]
    grids = {}
    with TestClient(create_app(settings, runtime=runtime)) as client:
        deadline = time.monotonic() + 120
        while client.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline, client.get("/readyz").text
            time.sleep(0.1)
        for name, folder in (("full", FRAME_DIR), ("quarter", quarter)):
            out = tmp_path / f"{name}.npz"
            assert main(["predict", "--model", str(model), "--images", str(folder), "--calib",
                         str(FRAME_DIR / "calib.json"), "--out", str(out)]) == 0
            predicted = np.load(out)["occupancy"]
            fed.clear()
            served = _serve_folder(client, folder, calib_bytes)
            np.testing.assert_array_equal(served, predicted)
            grids[name] = served
            (inputs,), = fed
            got_K = inputs.intrinsics[0]
            # the 1600x900 JPEGs are decoded at quarter scale (tiny), the 400x225 PNGs whole: both fed 400x225
            assert inputs.images.shape == (1, 6, 225, 400, 3)
            np.testing.assert_array_equal(got_K, calibration_arrays(calib, 400, 225)[0])
    K_full, K_quarter = calibration_arrays(calib, 1600, 900)[0], calibration_arrays(calib, 400, 225)[0]
    np.testing.assert_allclose(K_quarter[:, :2, :2], K_full[:, :2, :2] / 4, rtol=1e-6)
    np.testing.assert_allclose(K_quarter[:, :2, 2], (K_full[:, :2, 2] + 0.5) / 4 - 0.5, rtol=1e-6)   # pixel centres
    assert np.mean(grids["full"] != 17) > 0.005                         # a trained model: an occupied grid
    assert np.mean(grids["full"] == grids["quarter"]) > 0.99               # resizing first changes little
