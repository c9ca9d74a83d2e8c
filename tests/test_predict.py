"""`occflownet predict`: the torch-free ONNX path, the torch paths, their agreement (on a trained model whose grid
has occupied voxels), the same inputs and grid as the server, outputs and errors."""
import io
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from exported_models import FRAME, SEED, exported_tiny, exported_trained_tiny, frame_available, trained_tiny_checkpoint
from occflownet.export.parity import compare
from occflownet.cli import main
from occflownet.occ3d import CAMERAS, CLASS_COLORS, FREE, GRID
from occflownet.contract import calibration_arrays
from occflownet.pictures import top_down
from occflownet.predict import load_image_folder
from occflownet.rig import default_rig

needs_frame = pytest.mark.skipif(not frame_available(), reason=f"real frame not found at {FRAME}")


@pytest.fixture(scope="module")
def onnx_prediction(tmp_path_factory):
    """`predict --model` on the real frame in a fresh interpreter that must never import torch."""
    if not frame_available():
        pytest.skip(f"real frame not found at {FRAME}")
    path = exported_tiny()[0]
    out = tmp_path_factory.mktemp("predict")
    code = ("import sys; from occflownet.cli import main; "
            f"rc = main(['predict', '--model', {str(path)!r}, '--images', {str(FRAME)!r}, "
            f"'--calib', {str(FRAME / 'calib.json')!r}, '--out', {str(out / 'grid.npz')!r}, "
            f"'--png', {str(out / 'bev.png')!r}]); "
            "assert 'torch' not in sys.modules, 'predict --model imported torch'; sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "occupied voxels" in proc.stdout
    return out


def test_model_path_writes_grid_and_png_without_torch(onnx_prediction):
    import cv2

    grid = np.load(onnx_prediction / "grid.npz")
    assert grid["occupancy"].shape == GRID.shape and grid["occupancy"].dtype == np.uint8
    assert grid["density"].shape == GRID.shape and grid["density"].dtype == np.float32
    png = cv2.imread(str(onnx_prediction / "bev.png"))
    assert png.shape == (400, 400, 3)


@needs_frame
def test_random_init_torch_and_onnx_agree_on_the_real_frame(onnx_prediction, tmp_path, capsys):
    out = tmp_path / "torch.npz"
    rc = main(["predict", "--preset", "tiny", "--random-init", "--seed", str(SEED), "--images", str(FRAME),
               "--calib", str(FRAME / "calib.json"), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    a, b = np.load(out), np.load(onnx_prediction / "grid.npz")
    case = compare(a["occupancy"], a["density"], b["occupancy"], b["density"], 0.35, "cli", ())
    assert case.ok, case.describe()


def _occupied(occupancy: np.ndarray) -> float:
    return float((occupancy != FREE).mean())


@needs_frame
def test_trained_torch_and_onnx_agree_on_the_real_frame(tmp_path, capsys):
    """`predict --checkpoint` (torch) and `predict --model` (its export, onnxruntime) on a trained model whose grid
    has occupied voxels of several classes (1.5 % on the real frame): the same class everywhere except where σ is
    within float noise of τ, the densities within 1e-5 (measured 8.6e-7; different kernels: a tolerance, not
    equality)."""
    path = exported_trained_tiny()[0]
    outs = {}
    for name, args in (("torch", ["--checkpoint", str(trained_tiny_checkpoint())]), ("onnx", ["--model", str(path)])):
        outs[name] = tmp_path / f"{name}.npz"
        rc = main(["predict", *args, "--images", str(FRAME), "--calib", str(FRAME / "calib.json"),
                   "--out", str(outs[name])])
        assert rc == 0, capsys.readouterr().err
    a, b = np.load(outs["torch"]), np.load(outs["onnx"])
    assert 0.005 < _occupied(a["occupancy"]) < 0.2, _occupied(a["occupancy"])      # a grid worth comparing
    assert len(np.unique(a["occupancy"])) >= 3                                    # free + at least two classes
    differ = a["occupancy"] != b["occupancy"]
    near = np.abs(a["density"] - exported_trained_tiny()[2].cfg.threshold) < 1e-5      # where a flip is float noise
    assert not (differ & ~near).any(), f"{int((differ & ~near).sum())} voxels away from τ differ"
    assert float(np.abs(a["density"] - b["density"]).max()) <= 1e-5


@needs_frame
def test_checkpoint_path_matches_the_seeded_preset(tmp_path):
    from occflownet.model import save_checkpoint

    model = exported_tiny()[2]
    ckpt = save_checkpoint(tmp_path / "m.pt", model, model.cfg)
    for args, name in ((["--checkpoint", str(ckpt)], "a"), (["--preset", "tiny", "--random-init", "--seed",
                                                               str(SEED)], "b")):
        assert main(["predict", *args, "--images", str(FRAME), "--calib", str(FRAME / "calib.json"),
                     "--out", str(tmp_path / f"{name}.npz")]) == 0
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert np.array_equal(a["occupancy"], b["occupancy"]) and np.array_equal(a["density"], b["density"])


def _write_folder(folder, width=64, height=48):
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    calib = default_rig(width, height)
    for i, cam in enumerate(calib["cameras"]):
        cv2.imwrite(str(folder / f"{cam}.jpg"), np.full((height, width, 3), 40 * i, np.uint8))
    (folder / "calib.json").write_text(json.dumps(calib))
    return folder


@needs_frame
def test_load_frame_decodes_the_six_images_in_parallel(monkeypatch):
    """Each decode waits at a barrier for all six: decoding one image after another breaks the barrier (a
    BrokenBarrierError once its guard against hanging runs out). The images equal one-by-one decodes (exact: the
    same decoder on the same bytes, at the same scale)."""
    import threading

    import occflownet.predict as predict
    from occflownet.contract import decode_rgb

    barrier = threading.Barrier(len(CAMERAS), timeout=60)
    decode = predict.decode_image

    def waiting(data, name, reduction):
        barrier.wait()
        return decode(data, name, reduction)

    monkeypatch.setattr(predict, "decode_image", waiting)
    frame = predict.load_frame(FRAME, (160, 288))
    assert frame.images.shape == (6, 225, 400, 3) and frame.reductions == (4,) * 6
    for i, cam in enumerate(CAMERAS):
        assert np.array_equal(frame.images[i], decode_rgb((FRAME / f"{cam}.jpg").read_bytes(), 4))


def test_bad_inputs_give_clear_errors(tmp_path, capsys):
    folder = _write_folder(tmp_path / "imgs")
    model = str(exported_tiny()[0])
    base = ["predict", "--model", model, "--images", str(folder), "--out", str(tmp_path / "g.npz")]
    (folder / "CAM_BACK.jpg").unlink()
    assert main(base + ["--calib", str(folder / "calib.json")]) == 1
    assert "CAM_BACK.jpg" in capsys.readouterr().err
    _write_folder(folder)
    (folder / "CAM_FRONT.jpg").write_bytes(b"not a jpeg")
    assert main(base + ["--calib", str(folder / "calib.json")]) == 1
    assert "CAM_FRONT.jpg" in capsys.readouterr().err
    _write_folder(folder)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"cameras": {"CAM_FRONT": {}}}))
    assert main(base + ["--calib", str(bad)]) == 1
    assert "bad.json" in capsys.readouterr().err
    assert main(["predict", "--preset", "tiny", "--images", str(folder), "--calib", str(bad),
                 "--out", "x.npz"]) == 2
    assert main(base + ["--calib", str(folder / "calib.json")]) == 0


def test_bev_picture_orientation():
    occ = np.full(GRID.shape, 17, np.uint8)
    occ[190, 100, 3] = 4          # a car 36 m ahead       → top of the picture, centre column
    occ[100, 190, 2] = 11         # road 36 m to the left  → left side, middle row
    occ[100, 190, 9] = 15         # ... under a building   → the highest voxel wins
    img = top_down(occ, scale=1, ego=None)
    assert img.shape == (200, 200, 3)
    assert (img[199 - 190, 199 - 100] == CLASS_COLORS[4]).all()
    assert (img[199 - 100, 199 - 190] == CLASS_COLORS[15]).all()
    assert (img[0, 0] == CLASS_COLORS[17]).all()


def test_calibration_is_rescaled_to_the_image_size():
    K_small = calibration_arrays(default_rig(480, 270), 1600, 900)[0]
    K_native = calibration_arrays(default_rig(1600, 900))[0]
    assert np.allclose(K_small[:, :2, :2], K_native[:, :2, :2], rtol=1e-6)
    # principal point: (c + 0.5) · s − 0.5 (pixel centres)
    assert np.allclose(K_small[:, 0, 2], (240 + 0.5) * 1600 / 480 - 0.5)
    with pytest.raises(ValueError, match="aspect ratio"):
        calibration_arrays(default_rig(480, 270), 1000, 1000)


@needs_frame
def test_load_image_folder_reads_rgb_in_camera_order():
    import cv2

    images = load_image_folder(FRAME)
    assert images.shape == (6, 900, 1600, 3) and images.dtype == np.uint8
    for i, cam in enumerate(["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                             "CAM_BACK_RIGHT"]):
        assert np.array_equal(images[i], cv2.imread(str(FRAME / f"{cam}.jpg"))[:, :, ::-1])


@needs_frame
def test_jpegs_are_decoded_at_the_smallest_scale_that_holds_the_network_input():
    """The contract's reduced-scale rule on the real frame: tiny (160x288) gets the JPEGs at 1/4 (400x225; 1/8,
    200x113, would not hold 288 columns), base (256x704) at 1/2 (800x450); a PNG and a small JPEG are whole. The
    reduced decode is the n x n block average of the whole one: it matches cv2.resize(INTER_AREA) of the whole decode
    (the pixel-centre rule with s = 1/n, the intrinsics' rule) to half a grey level, 3-7x closer than the same
    average taken one stored pixel to the right."""
    import cv2

    from occflownet.contract import ImageHeader, decode_reduction, holding_reductions
    from occflownet.predict import load_frame

    assert decode_reduction(ImageHeader("png", 1600, 900, 33), (160, 288)) == 1
    assert decode_reduction(ImageHeader("jpeg", 3200, 1800, 0), (160, 288)) == 8
    assert decode_reduction(ImageHeader("jpeg", 480, 270, 0), (160, 288)) == 1      # 240x135 holds no 160 rows
    assert decode_reduction(ImageHeader("jpeg", 1600, 900, 0), (256, 704)) == 2     # 400 columns < 704
    assert holding_reductions(1600, 900, (160, 288)) == [1, 2, 4] and holding_reductions(400, 200, (256, 704)) == [1]
    assert load_frame(FRAME).images.shape == (6, 900, 1600, 3)
    whole = load_image_folder(FRAME).astype(np.float32)
    calib = json.loads((FRAME / "calib.json").read_text())
    K_whole, _ = calibration_arrays(calib, 1600, 900)
    for input_size, n in (((160, 288), 4), ((256, 704), 2)):
        frame = load_frame(FRAME, input_size)
        assert frame.reductions == (n,) * 6 and frame.sizes == ((1600, 900),) * 6
        assert frame.images.shape == (6, 900 // n, 1600 // n, 3)
        for i in range(6):
            size = (1600 // n, 900 // n)
            area = cv2.resize(whole[i], size, interpolation=cv2.INTER_AREA)
            shifted = cv2.resize(np.roll(whole[i], -1, axis=1), size, interpolation=cv2.INTER_AREA)
            err, err_shifted = (np.abs(frame.images[i] - a)[5:-5, 5:-5].mean() for a in (area, shifted))
            assert err < 0.5 and err_shifted > 3 * err, (n, i, err, err_shifted)   # 0.31-0.40 vs 1.4-2.8
        K = frame.inputs(calib).intrinsics[0]
        np.testing.assert_allclose(K[:, :2, :2], K_whole[:, :2, :2] / n, rtol=1e-6)
        np.testing.assert_allclose(K[:, :2, 2], (K_whole[:, :2, 2] + 0.5) / n - 0.5, rtol=1e-6)


def _png_and_five_jpegs(folder):
    """The real frame with CAM_FRONT as a lossless PNG of the same 1600x900 size and five JPEGs, and calib.json."""
    import cv2

    from occflownet.contract import decode_rgb

    folder.mkdir()
    for cam in CAMERAS:
        data = (FRAME / f"{cam}.jpg").read_bytes()
        if cam == "CAM_FRONT":
            assert cv2.imwrite(str(folder / "CAM_FRONT.png"), decode_rgb(data)[:, :, ::-1])
        else:
            (folder / f"{cam}.jpg").write_bytes(data)
    shutil.copy(FRAME / "calib.json", folder / "calib.json")
    return folder


def _server_inputs(model, folder):
    """The model inputs the server builds for the six files of ``folder`` and its calib.json, by its own functions
    in its order (serve/routers/occupancy.py: headers, the 1/n of each, the frame's size and calibration, then each
    image decoded into its slice of the tensor)."""
    from occflownet.serve.decode import check_header, decode_image, decode_reduction
    from occflownet.serve.model_runtime import ModelRuntime
    from occflownet.serve.settings import ServeSettings

    runtime = ModelRuntime.load(model, ServeSettings(model_path=str(model), intra_op_threads=1))
    files = {cam: next(folder.glob(f"{cam}.*")).read_bytes() for cam in CAMERAS}
    headers = [check_header(cam, files[cam], 1 << 24) for cam in CAMERAS]
    reductions = [decode_reduction(h, runtime.metadata.input_size) for h in headers]
    frame = runtime.frame((folder / "calib.json").read_bytes(), [(h.width, h.height) for h in headers], reductions)
    images = np.empty(frame.image_shape, np.uint8)
    for i, cam in enumerate(CAMERAS):
        decode_image(cam, files[cam], 1 << 24, images[i], reductions[i])
    return frame.inputs(images)


@needs_frame
def test_a_png_among_jpegs_gets_the_servers_inputs(tmp_path):
    """CAM_FRONT.png and five JPEGs of the same 1600x900 size: the PNG is decoded whole, the JPEGs at 1/4 (tiny),
    and the PNG is resized to their 400x225 with its intrinsics for that size, as the server does: the same
    images, intrinsics and cam2ego, exactly (the same decoders, resize and rescaling run on the same bytes)."""
    from occflownet.contract import decode_rgb, resize_rgb
    from occflownet.predict import load_frame

    folder = _png_and_five_jpegs(tmp_path / "mixed")
    model = exported_tiny()[0]
    frame = load_frame(folder, exported_tiny()[2].cfg.input_size)
    assert frame.reductions == (1, 4, 4, 4, 4, 4) and frame.sizes == ((1600, 900),) * 6
    assert frame.images.shape == (6, 225, 400, 3)
    whole = decode_rgb((folder / "CAM_FRONT.png").read_bytes())
    np.testing.assert_array_equal(frame.images[0], resize_rgb(whole, (400, 225)))
    ours = frame.inputs(json.loads((folder / "calib.json").read_text()))
    theirs = _server_inputs(model, folder)
    for name in ("images", "intrinsics", "cam2ego"):
        np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), err_msg=name)
    K, _ = calibration_arrays(json.loads((FRAME / "calib.json").read_text()), 400, 225)    # 1600x900 → 400x225
    np.testing.assert_allclose(ours.intrinsics[0], K, rtol=1e-6)


@needs_frame
def test_predict_and_the_server_give_the_same_grid_for_a_png_among_jpegs(tmp_path, capsys):
    """The same six files (a PNG among five JPEGs) through `occflownet predict --model` and `POST /v1/occupancy`
    on a trained model (occupied voxels of several classes): the same grid. Exact: both run the same inputs through
    onnxruntime sessions with the same options and one thread, so the same kernels in the same order."""
    from serve_fixtures import wait_app_ready
    from starlette.testclient import TestClient

    from occflownet.serve.app import create_app
    from occflownet.serve.settings import ServeSettings

    folder = _png_and_five_jpegs(tmp_path / "mixed")
    model = exported_trained_tiny()[0]
    out = tmp_path / "grid.npz"
    rc = main(["predict", "--model", str(model), "--images", str(folder), "--calib", str(folder / "calib.json"),
               "--out", str(out), "--threads", "1"])
    assert rc == 0, capsys.readouterr().err
    ours = np.load(out)["occupancy"]
    files = {cam: (p.name, p.read_bytes(), "image/png" if p.suffix == ".png" else "image/jpeg")
             for cam, p in ((cam, next(folder.glob(f"{cam}.*"))) for cam in CAMERAS)}
    files["calibration"] = ("calib.json", (folder / "calib.json").read_bytes(), "application/json")
    app = create_app(ServeSettings(model_path=str(model), intra_op_threads=1, max_inflight=1))
    with TestClient(app) as client:
        wait_app_ready(client, timeout=120)
        r = client.post("/v1/occupancy", files=files, headers={"Accept": "application/x-npy"})
    assert r.status_code == 200, r.text[:500]
    theirs = np.load(io.BytesIO(r.content))
    assert 0.005 < _occupied(ours) < 0.2 and len(np.unique(ours)) >= 3, _occupied(ours)
    np.testing.assert_array_equal(ours, theirs)


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with an EXIF APP1 segment whose IFD0 holds only the Orientation tag (0x0112)."""
    import struct

    tiff = (b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
            + struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack("<I", 0))
    app1 = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:]


def test_exif_orientation_is_ignored_everywhere(tmp_path):
    """The contract's image rule: pixels as stored, EXIF orientation ignored, in predict, training data and the
    server alike (the calibration describes the stored pixel grid)."""
    import cv2

    from occflownet.data.loaders import load_image
    from occflownet.predict import decode_image
    from occflownet.serve.decode import decode_image as serve_decode

    img = np.zeros((20, 40, 3), np.uint8)
    img[:, :20] = (255, 0, 0)                                    # left half red (RGB)
    ok, buf = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    rotated = _with_exif_orientation(buf.tobytes(), 6)          # "rotate 90° clockwise to view"
    assert cv2.imdecode(np.frombuffer(rotated, np.uint8), cv2.IMREAD_COLOR).shape == (40, 20, 3)  # a viewer rotates
    (tmp_path / "a.jpg").write_bytes(rotated)
    for rgb in (decode_image(rotated), load_image(tmp_path, "a.jpg"), serve_decode("CAM_FRONT", rotated, 10_000)):
        assert rgb.shape == (20, 40, 3)
        assert rgb[10, 5, 0] > 200 and rgb[10, 35, 0] < 60        # red stays on the left
