"""The HTTP API in-process (FastAPI TestClient) against the fake contract-v1 model: answers, formats, errors."""
import base64
import io
import json
import re
import subprocess
import sys
import threading

import cv2
import numpy as np
import pytest
from serve_fixtures import (FRAME_DIR, build_fake_model, camera_slab, encode_image, fake_pattern, fake_reference,
                            image_files, metric_samples, real_frame_files, synthetic_images, wait_app_ready)
from starlette.testclient import TestClient

from occflownet.contract import validate_calibration
from occflownet.occ3d import CAMERAS, CLASS_COLORS, FREE
from occflownet.rig import default_rig
from occflownet.serve.app import create_app
from occflownet.pictures import top_down
from occflownet.serve.model_runtime import ModelLoadError, ModelRuntime
from occflownet.serve.settings import ServeSettings

SIZE = (96, 54)  # same aspect as the fake model's 480x270 default calibration


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return build_fake_model(tmp_path_factory.mktemp("serve") / "fake.onnx")


@pytest.fixture(scope="module")
def client(model_path):
    app = create_app(ServeSettings(model_path=str(model_path), max_body_bytes=2_000_000,
                                   max_image_pixels=200_000))
    with TestClient(app) as c:
        wait_app_ready(c)
        yield c


IMAGES = synthetic_images(SIZE)


def _expected(images=IMAGES, calib=None):
    """The grid the server must answer, computed with the contract directly (calib None: the fake model's default
    calibration, 480x270)."""
    cal = validate_calibration(default_rig(480, 270) if calib is None else calib, CAMERAS)
    K, T = cal.arrays_for([(im.shape[1], im.shape[0]) for im in images])
    return fake_reference(np.stack(images), K, T)


def _grid(response):
    assert response.status_code == 200, response.text
    return np.frombuffer(base64.b64decode(response.json()["occupancy_base64"]), np.uint8).reshape(200, 200, 16)


def assert_valid_request(client):
    """The request every bad one is followed by: it must still succeed with the right grid."""
    np.testing.assert_array_equal(_grid(client.post("/v1/occupancy", files=image_files(IMAGES))), _expected())


def assert_error(response, status, code=None, match=None):
    assert response.status_code == status, response.text
    err = response.json()["error"]
    assert set(err) == {"code", "message"}
    if code:
        assert err["code"] == code, err
    if match:
        assert match in err["message"], err


# ---------------------------------------------------------------- the happy paths

def test_probes_metadata_and_default_calibration_answer(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json()["status"] == "ready"
    md = client.get("/v1/metadata").json()
    assert md["cameras"] == list(CAMERAS) and md["free_index"] == FREE and len(md["classes"]) == 18
    assert md["model"]["preset"] == "fake" and md["model"]["onnx_contract"] == "v1" and len(md["model"]["sha256"]) == 64
    assert md["default_calibration"]["image_size"] == [480, 270]
    # default calibration, 96x54 images: intrinsics must be scaled by 0.2 (the fake model's output depends on fx/W)
    r = client.post("/v1/occupancy", files=image_files(IMAGES))
    grid = _grid(r)
    np.testing.assert_array_equal(grid, _expected())
    j = r.json()
    assert j["shape"] == [200, 200, 16] and j["dtype"] == "uint8" and j["axes"] == ["x", "y", "z"]
    assert j["classes"][FREE] == "free" and j["grid"]["voxel_size"] == 0.4
    assert j["class_counts"] == {name: int((grid == i).sum()) for i, name in enumerate(j["classes"])}
    assert {"decode", "queue", "inference", "encode", "total"} <= set(j["timings_ms"])
    assert "inference;dur=" in r.headers["server-timing"]


def test_each_camera_part_reaches_its_own_camera_of_the_model(client):
    """Known answer, without the numpy twin: the fake model's classes in the k-th sixth of the grid along x are
    (P + floor(mean of camera k's top image row)) mod 17, k in the model's camera order; the six test images' top
    rows differ, so a part fed to another camera's place changes the classes of two slabs. And the same six
    images sent with two cameras' images swapped answer the same grid with those two slabs' classes swapped."""
    top = [int(np.floor(im[0].astype(np.float64).mean())) for im in IMAGES]
    assert len(set(top)) == 6                                          # precondition: the cameras differ
    grid = _grid(client.post("/v1/occupancy", files=image_files(IMAGES)))
    pattern = fake_pattern()
    for k, cam in enumerate(CAMERAS):
        slab = camera_slab(np.arange(200)) == k
        occupied = grid[slab] != FREE
        assert occupied.sum() > 1000, cam
        expected = (pattern[slab].astype(np.int64) + top[k]) % 17
        np.testing.assert_array_equal(grid[slab][occupied], expected[occupied], err_msg=cam)
    swapped = list(IMAGES)
    swapped[0], swapped[3] = IMAGES[3], IMAGES[0]                       # CAM_FRONT's and CAM_BACK's images
    other = _grid(client.post("/v1/occupancy", files=image_files(swapped)))
    assert (other != FREE).sum() == (grid != FREE).sum()               # same pixels: same occupied voxels
    changed = np.unique(camera_slab(np.nonzero((other != grid).any(axis=(1, 2)))[0]))
    assert changed.tolist() == [0, 3]


def test_unscaled_intrinsics_would_change_the_answer(client):
    # guards the test above: feeding the 480-px intrinsics for 96-px images gives a different grid
    calib = default_rig(480, 270)
    calib.pop("image_size")                                  # "take these intrinsics as they are"
    r = client.post("/v1/occupancy", files=image_files(IMAGES) | {"calibration": (None, json.dumps(calib))})
    assert not np.array_equal(_grid(r), _expected())
    np.testing.assert_array_equal(_grid(r), _expected(calib=calib))


def test_every_format_round_trips_to_the_same_grid(client):
    files = image_files(IMAGES, ".jpg")
    grid = _grid(client.post("/v1/occupancy", files=files))
    r = client.post("/v1/occupancy", files=files, headers={"Accept": "application/octet-stream"})
    assert r.headers["content-type"] == "application/octet-stream" and len(r.content) == 640_000
    shape = tuple(int(v) for v in r.headers["x-occupancy-shape"].split(","))
    np.testing.assert_array_equal(np.frombuffer(r.content, np.uint8).reshape(shape), grid)
    r = client.post("/v1/occupancy", files=files, headers={"Accept": "application/x-npy"})
    np.testing.assert_array_equal(np.load(io.BytesIO(r.content)), grid)
    r = client.post("/v1/occupancy", files=files, headers={"Accept": "image/png"})
    assert r.headers["content-type"] == "image/png"
    picture = cv2.cvtColor(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(picture, top_down(grid, CLASS_COLORS, FREE))


def test_explicit_calibration_and_real_frame(client):
    if not FRAME_DIR.is_dir():
        pytest.skip(f"shared real frame not found at {FRAME_DIR}")
    files, calib = real_frame_files()
    # 1600x900 images are over this client's 200,000-pixel limit: refused from the header, camera named
    assert_error(client.post("/v1/occupancy", files=files), 413, "image_too_large", "CAM_FRONT: image is 1600x900")
    assert_valid_request(client)
    small = {cam: cv2.resize(cv2.imread(str(FRAME_DIR / f"{cam}.jpg"))[..., ::-1], (320, 180),
                             interpolation=cv2.INTER_AREA) for cam in CAMERAS}
    calib_json = json.loads(calib)
    r = client.post("/v1/occupancy", files=image_files(list(small.values()), ".png") | {"calibration": (None, calib)})
    np.testing.assert_array_equal(_grid(r), _expected(list(small.values()), calib_json))


def test_images_of_different_sizes_are_resized_to_the_common_size(client):
    big_front = cv2.resize(IMAGES[0], (192, 108), interpolation=cv2.INTER_LINEAR)
    files = image_files([big_front] + IMAGES[1:])
    shrunk = cv2.resize(big_front, SIZE, interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(_grid(client.post("/v1/occupancy", files=files)), _expected([shrunk] + IMAGES[1:]))


def test_graph_with_a_fixed_image_size_gets_resized_images(tmp_path):
    path = build_fake_model(tmp_path / "fixed.onnx", fixed_hw=(54, 96))
    big = synthetic_images((192, 108))
    with TestClient(create_app(ServeSettings(model_path=str(path)))) as c:
        wait_app_ready(c)
        shrunk = [cv2.resize(im, SIZE, interpolation=cv2.INTER_AREA) for im in big]
        np.testing.assert_array_equal(_grid(c.post("/v1/occupancy", files=image_files(big))), _expected(shrunk))


def test_calibration_part_sent_as_a_file_with_json_type(client):
    calib = default_rig(96, 54)
    files = image_files(IMAGES) | {"calibration": ("calib.json", json.dumps(calib).encode(), "application/json")}
    np.testing.assert_array_equal(_grid(client.post("/v1/occupancy", files=files)), _expected())


# ---------------------------------------------------------------- bad requests, each followed by a good one

def _drop(name):
    return {k: v for k, v in image_files(IMAGES).items() if k != name}


@pytest.mark.parametrize("files, code, match", [
    (_drop("CAM_BACK"), "missing_part", "CAM_BACK"),
    (image_files(IMAGES) | {"CAM_TOP": ("t.png", b"x", "image/png")}, "unexpected_part", "'CAM_TOP'"),
    (_drop("CAM_FRONT") | {"cam_front": ("f.png", encode_image(IMAGES[0]), "image/png")}, "unexpected_part",
     "'cam_front'"),
    ({"calibration": (None, json.dumps(default_rig(96, 54)))}, "missing_part", "CAM_FRONT, CAM_FRONT_RIGHT"),
])
def test_wrong_parts_give_422(client, files, code, match):
    assert_error(client.post("/v1/occupancy", files=files), 422, code, match)
    assert_valid_request(client)


def test_duplicate_part_gives_422(client):
    files = list(image_files(IMAGES).items()) + [("CAM_BACK", ("again.png", encode_image(IMAGES[3]), "image/png"))]
    assert_error(client.post("/v1/occupancy", files=files), 422, "duplicate_part", "'CAM_BACK'")
    assert_valid_request(client)


@pytest.mark.parametrize("camera, payload, match", [
    ("CAM_FRONT_RIGHT", b"this is not an image", "CAM_FRONT_RIGHT: not a JPEG or PNG"),
    ("CAM_BACK", encode_image(IMAGES[3], ".jpg")[:-400], "CAM_BACK: truncated JPEG"),
    ("CAM_BACK_LEFT", encode_image(IMAGES[4], ".png")[:-300], "CAM_BACK_LEFT: truncated PNG"),
    ("CAM_FRONT", b"", "CAM_FRONT: image part is empty"),
])
def test_bad_images_give_400_naming_the_camera(client, camera, payload, match):
    files = image_files(IMAGES) | {camera: ("x.jpg", payload, "image/jpeg")}
    assert_error(client.post("/v1/occupancy", files=files), 400, "bad_image", match)
    assert_valid_request(client)


def test_image_header_over_pixel_limit_is_refused_before_decoding(client, monkeypatch):
    import struct

    data = bytearray(encode_image(IMAGES[2], ".png"))
    data[16:24] = struct.pack(">II", 20000, 20000)
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("decoded an over-limit image"))
    r = client.post("/v1/occupancy", files=image_files(IMAGES) | {"CAM_FRONT_LEFT": ("x.png", bytes(data))})
    assert_error(r, 413, "image_too_large", "CAM_FRONT_LEFT: image is 20000x20000")
    monkeypatch.undo()
    assert_valid_request(client)


def _calib_with(mutate):
    calib = default_rig(96, 54)
    mutate(calib["cameras"])
    return json.dumps(calib)


@pytest.mark.parametrize("calib, match", [
    (_calib_with(lambda c: c["CAM_FRONT"].update(intrinsic=[[1, 2, 3]])), "CAM_FRONT intrinsic must be (a )?3x3"),
    (_calib_with(lambda c: c["CAM_BACK"].update(cam2ego=[[1, 0], [0, 1]])), "CAM_BACK cam2ego must be (a )?4x4"),
    (_calib_with(lambda c: c["CAM_BACK_LEFT"]["intrinsic"][1].__setitem__(1, float("nan"))),
     r"CAM_BACK_LEFT intrinsic.*(NaN|nan)"),
    (_calib_with(lambda c: c["CAM_FRONT_RIGHT"].update(intrinsic=[[0, 0, 0], [0, 0, 0], [0, 0, 1]])), "singular"),
    (_calib_with(lambda c: c.pop("CAM_BACK_RIGHT")), "lacks camera CAM_BACK_RIGHT"),
    ("{not json", "not valid UTF-8 JSON"),
])
def test_bad_calibrations_give_400(client, calib, match):
    files = image_files(IMAGES) | {"calibration": (None, calib)}
    r = client.post("/v1/occupancy", files=files)
    assert_error(r, 400, "bad_calibration")
    assert re.search(match, r.json()["error"]["message"]), r.text
    assert_valid_request(client)


def test_default_calibration_with_another_aspect_ratio_gives_400(client):
    square = synthetic_images((64, 64))
    assert_error(client.post("/v1/occupancy", files=image_files(square)), 400, "bad_calibration",
                 "send a 'calibration' part")
    assert_valid_request(client)


@pytest.mark.parametrize("accept", ["text/html", "image/jpeg", "application/json;q=0"])
def test_unsupported_accept_gives_406(client, accept):
    assert_error(client.post("/v1/occupancy", files=image_files(IMAGES), headers={"Accept": accept}), 406,
                 "not_acceptable")
    assert_valid_request(client)


def test_wrong_content_type_gives_415(client):
    assert_error(client.post("/v1/occupancy", json={"CAM_FRONT": "x"}), 415, "unsupported_media_type")
    assert_error(client.post("/v1/occupancy", data={"CAM_FRONT": "x"}), 415)
    assert_error(client.post("/v1/occupancy", content=b"--x--", headers={"content-type": "multipart/form-data"}),
                 400, match="boundary")
    assert_valid_request(client)


def test_body_over_limit_gives_413(client):
    big = {"CAM_FRONT": ("f.png", b"\x89PNG" + b"\0" * 2_100_000, "image/png")}
    assert_error(client.post("/v1/occupancy", files=image_files(IMAGES) | big), 413, "payload_too_large")
    assert_valid_request(client)


def test_truncated_multipart_body_gives_400(client):
    import httpx

    req = httpx.Request("POST", "http://x/v1/occupancy", files=image_files(IMAGES))
    body = req.read()
    r = client.post("/v1/occupancy", content=body[:-5000], headers={"content-type": req.headers["content-type"]})
    assert r.status_code in (400, 422), r.text       # cut inside a part (400) or before the last parts (422)
    assert_valid_request(client)


def test_unknown_route_and_method_use_the_error_shape(client):
    assert_error(client.get("/v2/nothing"), 404, "not_found")
    assert_error(client.get("/v1/occupancy"), 405, "method_not_allowed")


# ---------------------------------------------------------------- metrics and OpenAPI

def test_metrics_count_routes_statuses_and_stages(client):
    client.post("/v1/occupancy", files=image_files(IMAGES), headers={"Accept": "text/html"})
    assert_valid_request(client)
    samples = metric_samples(client.get("/metrics").text)
    post = (("method", "POST"), ("route", "/v1/occupancy"))
    assert samples[("occflownet_http_requests_total", (*post, ("status", "406")))] >= 1
    assert samples[("occflownet_http_requests_total", (*post, ("status", "200")))] >= 1
    for stage in ("decode", "inference", "encode"):
        assert samples[("occflownet_stage_duration_seconds_count", (("stage", stage),))] >= 1
    assert samples[("occflownet_http_requests_in_flight", ())] == 1   # the /metrics request itself
    assert samples[("occflownet_model_ready", ())] == 1


def test_openapi_documents_routes_parts_and_binary_responses(client):
    spec = client.get("/openapi.json").json()
    assert {"/healthz", "/readyz", "/v1/metadata", "/metrics", "/v1/occupancy"} <= set(spec["paths"])
    post = spec["paths"]["/v1/occupancy"]["post"]
    schema = post["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert set(schema["properties"]) == set(CAMERAS) | {"calibration"} and set(schema["required"]) == set(CAMERAS)
    ok = post["responses"]["200"]
    assert {"application/json", "application/octet-stream", "application/x-npy", "image/png"} <= set(ok["content"])
    assert "X-Occupancy-Shape" in ok["headers"]
    assert {"400", "401", "406", "413", "415", "422", "503"} <= set(post["responses"])
    assert "text/plain" in spec["paths"]["/metrics"]["get"]["responses"]["200"]["content"]
    metadata = spec["paths"]["/v1/metadata"]["get"]["responses"]["200"]["content"]["application/json"]["schema"]
    assert metadata["$ref"] == "#/components/schemas/Metadata"
    assert {"ErrorResponse", "OccupancyJSON", "Health", "Ready"} <= set(spec["components"]["schemas"])


# ---------------------------------------------------------------- start-up, readiness, API key

def test_readyz_waits_for_the_warm_up_inference(model_path):
    runtime = ModelRuntime.load(model_path, ServeSettings())
    release = threading.Event()
    real_warm_up = runtime.warm_up
    runtime.warm_up = lambda: (release.wait(10), real_warm_up())
    with TestClient(create_app(ServeSettings(model_path=str(model_path)), runtime=runtime)) as c:
        assert c.get("/healthz").status_code == 200
        r = c.get("/readyz")
        assert_error(r, 503, "not_ready")
        assert r.headers["retry-after"] == "1"
        r = c.post("/v1/occupancy", files=image_files(IMAGES))
        assert_error(r, 503, "not_ready")
        release.set()
        wait_app_ready(c)
        assert_valid_request(c)


def test_api_key_required_except_for_probes(model_path):
    app = create_app(ServeSettings(model_path=str(model_path), api_key="s3cret-key"))
    with TestClient(app) as c:
        wait_app_ready(c)
        assert c.get("/healthz").status_code == 200
        for path in ("/v1/metadata", "/metrics", "/openapi.json"):
            assert_error(c.get(path), 401, "unauthorized")
            assert_error(c.get(path, headers={"Authorization": "Bearer wrong"}), 401)
            assert c.get(path, headers={"Authorization": "Bearer s3cret-key"}).status_code == 200
        r = c.post("/v1/occupancy", files=image_files(IMAGES))
        assert_error(r, 401)
        assert r.headers["www-authenticate"] == "Bearer"
        r = c.post("/v1/occupancy", files=image_files(IMAGES), headers={"Authorization": "Bearer s3cret-key"})
        np.testing.assert_array_equal(_grid(r), _expected())


def test_no_api_key_means_open(client):
    assert client.get("/v1/metadata").status_code == 200


@pytest.mark.parametrize("content, match", [(None, "model file not found"), (b"not onnx at all", "cannot load model")])
def test_missing_or_invalid_model_stops_start_up_naming_the_file(tmp_path, content, match):
    path = tmp_path / "model.onnx"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ModelLoadError, match=match) as info:
        with TestClient(create_app(ServeSettings(model_path=str(path)))):
            pass
    assert str(path) in str(info.value)


def test_model_breaking_the_contract_is_refused(tmp_path):
    path = build_fake_model(tmp_path / "v2.onnx", metadata={"onnx_contract": "v2"})
    with pytest.raises(ModelLoadError, match=f"{path}: invalid model metadata: onnx_contract"):
        ModelRuntime.load(path, ServeSettings())


def test_serve_never_imports_torch(model_path):
    code = f"""
import sys
from starlette.testclient import TestClient
from occflownet.serve.app import create_app
from occflownet.serve.client import wait_ready
from occflownet.serve.settings import ServeSettings
app = create_app(ServeSettings(model_path={str(model_path)!r}))
with TestClient(app) as c:
    def get(path):
        r = c.get(path)
        return r.status_code, r.content
    wait_ready('', 5, get=get, interval=0.01)
    import numpy as np, cv2
    img = cv2.imencode('.png', np.zeros((54, 96, 3), np.uint8))[1].tobytes()
    files = {{cam: (cam + '.png', img, 'image/png') for cam in {list(CAMERAS)!r}}}
    assert c.post('/v1/occupancy', files=files).status_code == 200
bad = [m for m in ('torch', 'onnx', 'export', 'occflownet.model') if m in sys.modules]
assert not bad, f'serve imported {{bad}}'
"""
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_the_routes_parts_are_one_definition(client):
    """The OpenAPI request body is written from the parts the reader allows (serve/routers/occupancy.py)."""
    from occflownet.serve.form import openapi_request_body
    from occflownet.serve.routers.occupancy import occupancy_parts

    spec = client.get("/openapi.json").json()["paths"]["/v1/occupancy"]["post"]["requestBody"]
    parts = occupancy_parts(CAMERAS, 1000)
    assert spec == openapi_request_body(parts)
    form = spec["content"]["multipart/form-data"]
    assert form["schema"]["properties"]["CAM_FRONT"]["format"] == "binary"
    assert "format" not in form["schema"]["properties"]["calibration"]                 # a file or a plain field
    assert form["encoding"]["calibration"] == {"contentType": "application/json"}
    assert parts["calibration"].limit == 1024 * 1024 and parts["CAM_BACK"].limit == 1000
