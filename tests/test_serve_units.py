"""Unit tests of serve/ pieces: image headers, calibration, Accept negotiation, encoders, metrics, settings, limits,
the ready-wait helper."""
import asyncio
import io
import json
import os
import struct
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from serve_fixtures import FRAME_DIR, encode_image, fake_metadata, metric_samples, synthetic_images

from occflownet.occ3d import CAMERAS, CLASS_COLORS, FREE
from occflownet.rig import default_rig
from occflownet.contract import CalibrationError, ContractError, calibration_json, parse_metadata, scale_intrinsics
from occflownet.serve.calibration import request_calibration
from occflownet.serve.client import ServerNotReady, wait_ready
from occflownet.serve.decode import ImageError, check_header, common_size, decode_image, image_header
from occflownet.pictures import top_down
from occflownet.serve.encode import NotAcceptable, encode, negotiate
from occflownet.serve.limits import (BodyLimitsMiddleware, BodyTimeout, InferenceGate, Saturated, ShuttingDown,
                                     TooManyUploads, Uploads)
from occflownet.serve.metrics import Metrics
from occflownet.serve.settings import DEFAULT_MAX_QUEUE, ServeSettings, SettingsError, env_name

REPO = Path(__file__).resolve().parents[1]

RGB = synthetic_images((64, 36))[0]


# ---------------------------------------------------------------- image headers and decoding

@pytest.mark.parametrize("progressive", [0, 1])
def test_jpeg_header_size_baseline_and_progressive(progressive):
    ok, buf = cv2.imencode(".jpg", RGB, [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive])
    h = image_header(buf.tobytes())
    assert (h.format, h.width, h.height) == ("jpeg", 64, 36)


def test_jpeg_header_skips_exif_thumbnail():
    main = encode_image(RGB, ".jpg")
    thumb = encode_image(np.zeros((8, 16, 3), np.uint8), ".jpg")   # its own SOF (16x8) and EOI inside APP1
    payload = b"Exif\x00\x00" + thumb
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    data = main[:2] + app1 + main[2:]
    h = image_header(data)
    assert (h.width, h.height) == (64, 36)
    assert decode_image("CAM_FRONT", data, 10**6).shape == (36, 64, 3)
    # cut inside the scan data: the thumbnail's EOI (before the scan) must not count as the end marker
    with pytest.raises(ImageError, match="CAM_FRONT: truncated JPEG"):
        decode_image("CAM_FRONT", data[:len(data) - 200], 10**6)


def test_png_header_and_exact_decode():
    data = encode_image(RGB, ".png")
    h = image_header(data)
    assert (h.format, h.width, h.height) == ("png", 64, 36)
    np.testing.assert_array_equal(decode_image("CAM_BACK", data, 10**6), RGB)  # RGB order preserved


def test_real_frame_headers_match_decode():
    if not FRAME_DIR.is_dir():
        pytest.skip(f"shared real frame not found at {FRAME_DIR}")
    data = (FRAME_DIR / "CAM_FRONT.jpg").read_bytes()
    h = image_header(data)
    assert (h.width, h.height) == (1600, 900)
    assert decode_image("CAM_FRONT", data, 1600 * 900).shape == (900, 1600, 3)


@pytest.mark.parametrize("data, message", [
    (b"", "empty"),
    (b"GIF89a....", "not a JPEG or PNG"),
    (b"\xff\xd8\xff\xe0\x00", "truncated JPEG"),
    (b"\x89PNG\r\n\x1a\n\x00\x00", "truncated PNG"),
])
def test_bad_image_bytes_name_the_camera(data, message):
    with pytest.raises(ImageError, match=f"CAM_BACK_LEFT: .*{message}") as info:
        decode_image("CAM_BACK_LEFT", data, 10**6)
    assert info.value.status == 400


def test_truncated_png_is_refused():
    data = encode_image(RGB, ".png")
    with pytest.raises(ImageError, match="truncated PNG"):
        decode_image("CAM_FRONT", data[: len(data) // 2], 10**6)


def test_pixel_limit_is_checked_from_the_header_before_decoding(monkeypatch):
    data = bytearray(encode_image(RGB, ".png"))
    data[16:24] = struct.pack(">II", 20000, 20000)   # header claims 400 MP; the data is 64x36
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("decoder called for an over-limit image"))
    with pytest.raises(ImageError, match="CAM_FRONT: image is 20000x20000") as info:
        check_header("CAM_FRONT", bytes(data), 4096 * 4096)
    assert info.value.status == 413
    with pytest.raises(ImageError):
        decode_image("CAM_FRONT", bytes(data), 4096 * 4096)


def test_common_size_decode_into_place_and_intrinsics():
    assert common_size([(2, 1), (4, 2), (4, 2), (2, 1)]) == (2, 1)  # tie → earlier camera
    assert common_size([(2, 1), (4, 2), (4, 2)]) == (4, 2)
    small = synthetic_images((96, 54))
    big = cv2.resize(small[0], (192, 108), interpolation=cv2.INTER_LINEAR)
    frame = np.zeros((2, 54, 96, 3), np.uint8)
    decode_image("CAM_FRONT", encode_image(big), 10**6, out=frame[0])   # resized while decoded
    decode_image("CAM_BACK", encode_image(small[1]), 10**6, out=frame[1])  # decoded in place, untouched
    np.testing.assert_array_equal(frame[0], cv2.resize(big, (96, 54), interpolation=cv2.INTER_AREA))
    np.testing.assert_array_equal(frame[1], small[1])
    # CAM_FRONT's intrinsics are for its 192x108 image (pixel-centre rule: f·2, (c + 0.5)·2 − 0.5); resized to the
    # common size 96x54 its intrinsics are halved back exactly, in the one rescale; the others are unchanged
    K = np.tile(np.array([[100.0, 0, 48], [0, 100.0, 27], [0, 0, 1]]), (6, 1, 1))
    K[0] = scale_intrinsics(K[0], 2.0, 2.0)
    np.testing.assert_allclose(K[0], [[200, 0, 96.5], [0, 200, 54.5], [0, 0, 1]])
    calib = calibration_json(K, np.tile(np.eye(4), (6, 1, 1)), (96, 54))
    calib["cameras"]["CAM_FRONT"]["image_size"] = [192, 108]
    frame = request_calibration(_part(calib), _Meta, [(192, 108)] + [(96, 54)] * 5, size=(96, 54))
    assert frame.intrinsics.dtype == np.float32 and frame.size == (96, 54)
    np.testing.assert_allclose(frame.intrinsics, np.tile(K[1], (6, 1, 1)))


# ---------------------------------------------------------------- calibration of a request (rules: the contract's)

def _calib():
    return default_rig(480, 270)


class _Meta:
    cameras = CAMERAS
    default_calibration = default_rig(480, 270)


def _part(calib) -> bytes:
    return json.dumps(calib).encode()


@pytest.mark.parametrize("mutate, message", [
    (lambda c: c["cameras"]["CAM_FRONT"].update(intrinsic=[[1, 0], [0, 1]]), "CAM_FRONT intrinsic must be (a )?3x3"),
    (lambda c: c["cameras"]["CAM_BACK"].update(cam2ego=np.eye(3).tolist()), "CAM_BACK cam2ego must be (a )?4x4"),
    (lambda c: c["cameras"]["CAM_BACK"]["intrinsic"][0].__setitem__(0, float("nan")), "CAM_BACK intrinsic.*(NaN|nan)"),
    (lambda c: c["cameras"]["CAM_FRONT"]["cam2ego"][0].__setitem__(3, float("inf")), "CAM_FRONT cam2ego.*inf"),
    (lambda c: c["cameras"]["CAM_FRONT_LEFT"].update(intrinsic=np.zeros((3, 3)).tolist()), "singular"),
    (lambda c: c["cameras"]["CAM_FRONT_LEFT"]["intrinsic"][0].__setitem__(0, 0.0), "CAM_FRONT_LEFT .*singular"),
    (lambda c: c["cameras"].pop("CAM_BACK_RIGHT"), "lacks camera CAM_BACK_RIGHT"),
    (lambda c: c["cameras"]["CAM_FRONT"].pop("cam2ego"), "CAM_FRONT lacks 'cam2ego'"),
    (lambda c: c["cameras"]["CAM_FRONT"].update(intrinsic="abc"), "CAM_FRONT intrinsic"),
    (lambda c: c["cameras"]["CAM_FRONT"]["cam2ego"][0].__setitem__(0, 2.0), "not a proper rotation"),
    (lambda c: c.pop("cameras"), "no 'cameras'"),
])
def test_bad_calibration_parts_are_named(mutate, message):
    calib = _calib()
    mutate(calib)
    with pytest.raises(CalibrationError, match=message):
        request_calibration(_part(calib), _Meta, [(480, 270)] * 6)


def test_calibration_part_that_is_not_a_json_object_names_the_part():
    with pytest.raises(CalibrationError, match="calibration part is not valid UTF-8 JSON"):
        request_calibration(b"{nope", _Meta, [(480, 270)] * 6)
    with pytest.raises(CalibrationError, match="calibration part must be a JSON object"):
        request_calibration(b"[1, 2]", _Meta, [(480, 270)] * 6)


def test_default_calibration_scaled_for_same_aspect_and_refused_otherwise():
    frame = request_calibration(None, _Meta, [(960, 540)] * 6)
    K, T = frame.intrinsics, frame.cam2ego
    K480 = np.array(_calib()["cameras"]["CAM_FRONT"]["intrinsic"])
    # pixel-centre rule, as predict and the model's preprocessing: f' = 2f, c' = (c + 0.5)·2 − 0.5
    np.testing.assert_allclose(K[0], [[2 * K480[0, 0], 0, 2 * K480[0, 2] + 0.5],
                                      [0, 2 * K480[1, 1], 2 * K480[1, 2] + 0.5], [0, 0, 1]], rtol=1e-6)
    assert T.dtype == np.float32 and T.shape == (6, 4, 4)
    with pytest.raises(CalibrationError, match="CAM_FRONT: image is 500x500 but the model's default calibration is "
                                               "for 480x270 .*send a 'calibration' part"):
        request_calibration(None, _Meta, [(500, 500)] * 6)
    with pytest.raises(CalibrationError, match="CAM_FRONT: image is 500x500 but the request's calibration"):
        request_calibration(_part(_calib()), _Meta, [(500, 500)] * 6)


def test_request_calibration_without_size_is_taken_as_is():
    calib = _calib()
    calib.pop("image_size")
    K = request_calibration(_part(calib), _Meta, [(123, 77)] * 6).intrinsics
    np.testing.assert_allclose(K[0], np.array(calib["cameras"]["CAM_FRONT"]["intrinsic"]), rtol=1e-6)


def test_per_camera_image_size_overrides_top_level():
    calib = _calib()
    calib["cameras"]["CAM_BACK"]["image_size"] = [960, 540]
    K480 = np.array(calib["cameras"]["CAM_BACK"]["intrinsic"])
    calib["cameras"]["CAM_BACK"]["intrinsic"] = scale_intrinsics(K480, 2.0, 2.0).tolist()   # for 960x540
    K = request_calibration(_part(calib), _Meta, [(480, 270)] * 6).intrinsics
    np.testing.assert_allclose(K[3], np.array(_calib()["cameras"]["CAM_BACK"]["intrinsic"]), rtol=1e-6)


# ---------------------------------------------------------------- Accept negotiation and encoders

@pytest.mark.parametrize("accept, expected", [
    (None, "application/json"), ("", "application/json"), ("*/*", "application/json"),
    ("application/octet-stream", "application/octet-stream"), ("image/*", "image/png"),
    ("image/png;q=0.5, application/x-npy", "application/x-npy"),
    ("text/html, */*;q=0.1", "application/json"), ("application/x-npy;q=0, image/png", "image/png"),
    ("APPLICATION/JSON", "application/json"),
])
def test_negotiate(accept, expected):
    assert negotiate(accept) == expected


@pytest.mark.parametrize("accept", ["text/html", "application/xml", "image/jpeg", "application/json;q=0"])
def test_negotiate_refuses(accept):
    with pytest.raises(NotAcceptable):
        negotiate(accept)


class _MD:
    classes = tuple(fake_metadata()["classes"])
    free_index = FREE
    grid = fake_metadata()["grid"]
    class_colors = CLASS_COLORS
    preset = "fake"
    occflownet_version = "0"


def test_all_encoders_carry_the_same_grid():
    import base64

    grid = np.random.default_rng(3).integers(0, 18, (200, 200, 16), dtype=np.uint8)
    body, _ = encode("application/json", grid, _MD, {"decode": 1.0})
    j = json.loads(body)
    assert j["shape"] == [200, 200, 16] and j["free_index"] == 17 and sum(j["class_counts"].values()) == grid.size
    np.testing.assert_array_equal(np.frombuffer(base64.b64decode(j["occupancy_base64"]), np.uint8).reshape(j["shape"]),
                                  grid)
    raw, headers = encode("application/octet-stream", grid, _MD, {})
    assert len(raw) == 640_000 and headers["X-Occupancy-Shape"] == "200,200,16"
    np.testing.assert_array_equal(np.frombuffer(raw, np.uint8).reshape(200, 200, 16), grid)
    npy, _ = encode("application/x-npy", grid, _MD, {})
    np.testing.assert_array_equal(np.load(io.BytesIO(npy)), grid)
    png, _ = encode("image/png", grid, _MD, {})
    picture = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(picture, top_down(grid, CLASS_COLORS, FREE))


def test_top_down_orientation_and_highest_voxel():
    grid = np.full((200, 200, 16), FREE, np.uint8)
    grid[199, 199, 0] = 4           # car at +x (front), +y (left) corner, on the ground
    grid[199, 199, 5] = 15          # manmade above it: the top-most wins
    grid[0, 0, 3] = 7               # pedestrian at the rear right corner
    rgb = top_down(grid, CLASS_COLORS, FREE)
    assert rgb.shape == (400, 400, 3)
    np.testing.assert_array_equal(rgb[0, 0], CLASS_COLORS[15])       # image top-left = front-left
    np.testing.assert_array_equal(rgb[-1, -1], CLASS_COLORS[7])      # image bottom-right = rear-right
    np.testing.assert_array_equal(rgb[100, 300], CLASS_COLORS[FREE])
    np.testing.assert_array_equal(rgb[200, 200], [0, 0, 0])          # ego marker


# ---------------------------------------------------------------- metrics, settings, metadata

def test_metrics_exposition_counts_and_histograms():
    m = Metrics()
    m.request_started()
    m.request_finished("/v1/occupancy", "POST", 200, 0.07)
    m.observe_stage("inference", 0.05)
    m.observe_stage("inference", 2.0)
    m.reject("saturated")
    m.set_gate(3, 1)
    samples = metric_samples(m.render().decode())
    assert samples[("occflownet_http_requests_total",
                    (("method", "POST"), ("route", "/v1/occupancy"), ("status", "200")))] == 1
    assert samples[("occflownet_stage_duration_seconds_bucket", (("le", "0.05"), ("stage", "inference")))] == 1
    assert samples[("occflownet_stage_duration_seconds_bucket", (("le", "2.5"), ("stage", "inference")))] == 2
    assert samples[("occflownet_stage_duration_seconds_count", (("stage", "inference"),))] == 2
    assert samples[("occflownet_stage_duration_seconds_count", (("stage", "decode"),))] == 0     # every stage listed
    assert samples[("occflownet_rejected_total", (("reason", "saturated"),))] == 1
    assert samples[("occflownet_rejected_total", (("reason", "not_ready"),))] == 0
    assert samples[("occflownet_http_requests_in_flight", ())] == 0
    assert samples[("occflownet_inference_queue_depth", ())] == 3 and samples[("occflownet_inferences_running", ())] == 1
    assert samples[("occflownet_model_ready", ())] == 0
    m.set_ready()
    assert metric_samples(m.render().decode())[("occflownet_model_ready", ())] == 1
    assert not [name for name, _ in samples if name.endswith("_created")]


def test_multiprocess_dir_is_made_for_the_workers_and_removed(monkeypatch, tmp_path):
    from occflownet.serve.metrics import MULTIPROC_ENV, multiprocess_dir

    monkeypatch.delenv(MULTIPROC_ENV, raising=False)
    with multiprocess_dir() as folder:
        assert os.environ[MULTIPROC_ENV] == str(folder) and folder.is_dir()
        (folder / "counter_123.db").write_bytes(b"x")
    assert not folder.exists() and MULTIPROC_ENV not in os.environ
    given = tmp_path / "metrics"                                # the user's folder: kept, emptied of old files
    given.mkdir()
    (given / "counter_1.db").write_bytes(b"old")
    monkeypatch.setenv(MULTIPROC_ENV, str(given))
    with multiprocess_dir() as folder:
        assert folder == given and not list(given.glob("*.db"))
        (folder / "gauge_livesum_7.db").write_bytes(b"x")
    assert given.is_dir() and not list(given.glob("*.db")) and os.environ[MULTIPROC_ENV] == str(given)


def test_settings_from_env_and_resolution(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)                                 # no .env of the repository
    env = {"OCCFLOWNET_MODEL": "m.onnx", "OCCFLOWNET_MAX_QUEUE": "7", "OCCFLOWNET_WARMUP": "0",
           "OCCFLOWNET_INTRA_OP_THREADS": "1", "OCCFLOWNET_PROVIDERS": "A, B", "OCCFLOWNET_API_KEY": " "}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    s = ServeSettings.from_env()
    assert (s.model_path, s.max_queue, s.warmup, s.providers, s.api_key) == ("m.onnx", 7, False, ["A", "B"], None)
    assert ServeSettings.from_env(max_queue=2, model_path="other.onnx").max_queue == 2     # the command line wins
    r = s.resolved()
    assert r.intra_op_threads == 1 and r.max_inflight >= 1
    for k, v in r.to_env().items():
        monkeypatch.setenv(k, v)
    assert ServeSettings.from_env().resolved() == r
    monkeypatch.setenv("OCCFLOWNET_MAX_QUEUE", "many")
    with pytest.raises(SettingsError, match="OCCFLOWNET_MAX_QUEUE='many': Input should be a valid integer"):
        ServeSettings.from_env()
    monkeypatch.setenv("OCCFLOWNET_MAX_QUEUE", "")                  # empty = unset: the default
    assert ServeSettings.from_env().max_queue == DEFAULT_MAX_QUEUE
    monkeypatch.setenv("OCCFLOWNET_UI", "perhaps")
    with pytest.raises(SettingsError, match="OCCFLOWNET_UI='perhaps'"):
        ServeSettings.from_env()
    monkeypatch.delenv("OCCFLOWNET_UI")
    with pytest.raises(SettingsError, match="setting max_inflight=-1: .*greater than or equal to 1"):
        ServeSettings.from_env(max_inflight=-1)
    with pytest.raises(ValueError, match="max_inflight"):
        ServeSettings(max_inflight=-1)


def test_settings_read_a_dotenv_file(monkeypatch, tmp_path):
    for name in ServeSettings.model_fields:
        monkeypatch.delenv(env_name(name), raising=False)
    monkeypatch.chdir(tmp_path)
    (tmp_path / ".env").write_text("OCCFLOWNET_MODEL=/models/from-dotenv.onnx\nOCCFLOWNET_MAX_QUEUE=9\nOTHER=1\n")
    s = ServeSettings.from_env()
    assert (s.model_path, s.max_queue) == ("/models/from-dotenv.onnx", 9)
    monkeypatch.setenv("OCCFLOWNET_MAX_QUEUE", "3")                  # the environment wins over the file
    assert ServeSettings.from_env().max_queue == 3


def test_every_setting_is_documented():
    doc = (REPO / "docs" / "serve.md").read_text()
    for name, info in ServeSettings.model_fields.items():
        assert info.description and f"`{env_name(name)}" in doc, name


def _serve_args(*argv: str):
    from occflownet.cli import build_parser

    return build_parser().parse_args(["serve", *argv])


def _clean_environment(monkeypatch, tmp_path):
    for name in ServeSettings.model_fields:
        monkeypatch.delenv(env_name(name), raising=False)
    monkeypatch.chdir(tmp_path)                                 # no .env of the repository


def test_every_setting_but_the_api_key_is_reachable_from_the_command_line(monkeypatch, tmp_path):
    from occflownet.commands.serve import _settings

    _clean_environment(monkeypatch, tmp_path)
    given = {"model_path": "m.onnx", "max_body_bytes": 3 * 1024 * 1024, "max_image_pixels": 640 * 480,
             "intra_op_threads": 3, "max_inflight": 2, "max_queue": 0, "workers": 2, "ort_spin": True,
             "providers": ["A", "B"], "warmup": False, "ui": False, "max_uploads": 5, "body_timeout_s": 2.5,
             "shutdown_timeout_s": 3.0, "docs": True}
    assert set(given) == set(ServeSettings.model_fields) - {"api_key"}
    assert all(value != ServeSettings.model_fields[name].default for name, value in given.items())
    args = _serve_args("--model", "m.onnx", "--max-body-mb", "3", "--max-image-pixels", "307200", "--threads", "3",
                       "--max-inflight", "2", "--max-queue", "0", "--workers", "2", "--ort-spin", "--providers",
                       "A,B", "--no-warmup", "--no-ui", "--max-uploads", "5", "--body-timeout", "2.5",
                       "--shutdown-timeout", "3", "--docs")
    settings = _settings(args)
    assert {name: getattr(settings, name) for name in given} == given
    with pytest.raises(SystemExit):                             # the key: from the environment only
        _serve_args("--api-key", "secret")


def test_serve_options_left_unset_fall_back_to_the_environment_then_the_defaults(monkeypatch, tmp_path):
    from occflownet.commands.serve import _settings

    _clean_environment(monkeypatch, tmp_path)
    assert _settings(_serve_args()) == ServeSettings()
    assert _settings(_serve_args()).max_queue == DEFAULT_MAX_QUEUE
    monkeypatch.setenv("OCCFLOWNET_MAX_QUEUE", "9")
    monkeypatch.setenv("OCCFLOWNET_WARMUP", "0")
    assert (_settings(_serve_args()).max_queue, _settings(_serve_args()).warmup) == (9, False)
    assert (_settings(_serve_args("--max-queue", "2", "--warmup")).max_queue,
            _settings(_serve_args("--max-queue", "2", "--warmup")).warmup) == (2, True)   # the command line wins


def test_the_serve_help_shows_each_settings_default_and_variable():
    from occflownet.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "verb").choices["serve"]
    helps = {a.dest: a.help for a in sub._actions}
    helps["max_body_bytes"] = helps.pop("max_body_mb")
    for name, info in ServeSettings.model_fields.items():
        if name == "api_key":
            assert name not in helps
            continue
        assert helps[name].startswith(info.description) and f"${env_name(name)}" in helps[name], name
        if isinstance(info.default, bool):
            assert f"(default: {'on' if info.default else 'off'};" in helps[name], name
        elif isinstance(info.default, int):
            shown = info.default // (1024 * 1024) if name == "max_body_bytes" else info.default
            assert f"(default: {shown};" in helps[name], name
    assert "(default: CPUExecutionProvider;" in helps["providers"]


def test_fake_model_metadata_follows_the_contract():
    props = {k: json.dumps(v) for k, v in fake_metadata().items()}
    md = parse_metadata(props, "m.onnx")
    assert md.grid_shape == (200, 200, 16) and md.cameras == CAMERAS and md.class_colors.shape == (18, 3)
    for broken, message in ((props | {"onnx_contract": '"v2"'}, "speaks 'v1'"),
                            ({k: v for k, v in props.items() if k != "cameras"}, "lacks cameras"),
                            (props | {"class_colors": "[[1, 2, 3]]"}, "class_colors")):
        with pytest.raises(ContractError, match=f"m.onnx: .*{message}"):
            parse_metadata(broken, "m.onnx")


# ---------------------------------------------------------------- limits

def _run_middleware(limit, chunks, content_length=None):
    """Drive BodyLimitsMiddleware with an app that reads the whole body (chunked unless ``content_length``);
    → (status, chunks consumed)."""
    consumed = 0
    sent = []

    async def app(scope, receive, send):
        while True:
            message = await receive()
            if not message.get("more_body"):
                break
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    async def receive():
        nonlocal consumed
        consumed += 1
        return {"type": "http.request", "body": chunks[consumed - 1], "more_body": consumed < len(chunks)}

    async def send(message):
        sent.append(message)

    headers = ([(b"transfer-encoding", b"chunked")] if content_length is None
               else [(b"content-length", str(content_length).encode())])
    scope = {"type": "http", "method": "POST", "path": "/v1/occupancy", "headers": headers}
    asyncio.run(BodyLimitsMiddleware(app, limit, Uploads(4, 30.0))(scope, receive, send))
    return sent[0]["status"], consumed


def test_body_limit_declared_length_refused_without_reading():
    status, consumed = _run_middleware(1000, [b"x" * 100] * 50, content_length=5000)
    assert (status, consumed) == (413, 0)


def test_body_limit_streamed_body_stops_at_the_limit():
    status, consumed = _run_middleware(1000, [b"x" * 100] * 50)
    assert status == 413 and consumed == 11      # the 11th chunk passes 1000 bytes; the other 39 are never read
    assert _run_middleware(1000, [b"x" * 100] * 10) == (200, 10)


def test_gate_admission_and_retry_after():
    async def scenario():
        gate = InferenceGate(max_inflight=1, max_queue=1)
        gate.admit()
        gate.admit()
        with pytest.raises(Saturated) as info:
            gate.admit()
        assert info.value.retry_after == 1          # nothing measured yet
        async with gate.slot() as slot:
            assert gate.running == 1
            assert await gate.infer(slot, lambda x: x * 2, 21) == 42
        assert gate.running == 0
        gate.leave()
        gate.admit()                                 # room again
        gate.shutdown()
    asyncio.run(scenario())


def test_retry_after_is_the_mean_slot_time_times_the_waiting_over_the_slots():
    """Known answers with a clock the test sets: slots of 4 s then 9 s give the moving average 0.8·4 + 0.2·9 = 5 s;
    with two slots and five requests waiting, Retry-After = ⌈5 × (5 + 1) / 2⌉ = 15; with two of the five computing
    (three waiting), ⌈5 × (3 + 1) / 2⌉ = 10; a mean of 30 s caps it at 60."""
    now = [0.0]

    async def scenario():
        gate = InferenceGate(max_inflight=2, max_queue=3, clock=lambda: now[0])
        for seconds in (4.0, 9.0):
            gate.admit()
            async with gate.slot():
                now[0] += seconds
            gate.leave()
        for _ in range(5):
            gate.admit()
        with pytest.raises(Saturated) as info:
            gate.check()
        assert info.value.retry_after == 15
        assert gate.admitted == 5                                        # check() reserved nothing
        held = [gate.slot(), gate.slot()]
        for slot in held:
            await slot.__aenter__()
        assert gate.retry_after() == 10
        for slot in held:
            now[0] += 30.0
            await slot.__aexit__(None, None, None)
        # slots of 30 s and 60 s (both began at the same time): 0.8·(0.8·5 + 0.2·30) + 0.2·60 = 20 s
        assert gate._mean_s == pytest.approx(20.0)
        now[0] = 0.0
        gate._mean_s = 30.0
        assert gate.retry_after() == 60                                  # ⌈30 × 6 / 2⌉ = 90 → the cap
        gate.shutdown()
    asyncio.run(scenario())


@pytest.mark.parametrize("cores, workers, threads, expected", [
    (8, 1, 2, (2, 4)), (8, 1, None, (8, 1)), (8, 2, None, (4, 1)), (8, 2, 1, (1, 4)), (8, 4, 1, (1, 2)),
    (3, 2, None, (1, 1)), (8, 16, None, (1, 1)), (16, 2, 3, (3, 2)),
])
def test_resolved_threads_and_slots_from_the_cores(monkeypatch, cores, workers, threads, expected):
    """intra_op_threads = cores // workers unless given; max_inflight = max(1, cores // workers // threads)."""
    import occflownet.serve.settings as settings_module

    monkeypatch.setattr(settings_module, "available_cores", lambda: cores)
    r = ServeSettings(workers=workers, intra_op_threads=threads).resolved()
    assert (r.intra_op_threads, r.max_inflight) == expected
    assert ServeSettings(workers=workers, intra_op_threads=threads, max_inflight=3).resolved().max_inflight == 3


def test_uploads_are_counted_timed_and_drained():
    """Uploads: the count bound, the deadline of a receive that waits (408), and the drain (new ones 503 at once,
    waiting ones after the grace)."""
    async def scenario():
        uploads = Uploads(max_uploads=2, timeout_s=0.05)
        uploads.enter()
        uploads.enter()
        with pytest.raises(TooManyUploads):
            uploads.enter()
        uploads.leave()
        loop = asyncio.get_running_loop()
        never = asyncio.Event()

        async def stalled_receive():
            await never.wait()

        async def ready_receive():
            return {"type": "http.request", "body": b"x", "more_body": False}

        with pytest.raises(BodyTimeout):
            await uploads.receive(stalled_receive, loop.time() + 0.05)
        assert (await uploads.receive(ready_receive, loop.time() - 1))["body"] == b"x"   # a message ready wins
        waiting = asyncio.ensure_future(uploads.receive(stalled_receive, loop.time() + 60))
        await asyncio.sleep(0)
        uploads.drain(grace=0.01)
        with pytest.raises(ShuttingDown):
            uploads.enter()
        with pytest.raises(ShuttingDown):
            await waiting
    asyncio.run(scenario())


def test_gate_slot_outlives_a_cancelled_request_until_its_inference_ends():
    async def scenario():
        gate = InferenceGate(max_inflight=1, max_queue=0)
        release = threading.Event()

        async def request():
            async with gate.slot() as slot:
                await gate.infer(slot, release.wait, 10)

        task = asyncio.create_task(request())
        while gate.running == 0:
            await asyncio.sleep(0.001)
        await asyncio.sleep(0.02)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert gate.running == 1                     # the thread still computes: slot not given back yet
        release.set()
        for _ in range(500):
            if gate.running == 0:
                break
            await asyncio.sleep(0.01)
        assert gate.running == 0
        gate.shutdown()
    asyncio.run(scenario())


# ---------------------------------------------------------------- waiting for a server

def test_wait_ready_polls_until_200_and_returns_the_body():
    answers = iter([OSError("connection refused"), (503, b"warming up"), (200, b'{"status": "ready"}')])

    def get(url):
        assert url == "http://h/readyz"
        answer = next(answers)
        if isinstance(answer, Exception):
            raise answer
        return answer

    assert wait_ready("http://h", timeout=5, get=get, interval=0) == {"status": "ready"}


def test_wait_ready_names_the_last_answer_or_the_exited_process():
    with pytest.raises(ServerNotReady, match=r"http://h/readyz did not answer 200 within 0.05 s \(last: 503 busy\)"):
        wait_ready("http://h", timeout=0.05, get=lambda url: (503, b"busy"), interval=0.01)

    class Exited:
        returncode, stderr = 2, None

        def poll(self):
            return 2

    with pytest.raises(ServerNotReady, match="server exited with status 2"):
        wait_ready("http://h", timeout=5, proc=Exited(), get=lambda url: pytest.fail("polled a dead server"))
