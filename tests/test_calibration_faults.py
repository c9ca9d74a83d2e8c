"""The calibration fault battery: each bad calibration is refused on every path that reads calibration JSON, with a
message naming the field (the contract's functions, `occflownet predict`, the server here; the C++ runner in
tests/test_embed.py, which imports :data:`FAULTS`).

Each fault is a function of a valid calibration (a dict) that returns the bad calibration's JSON text, with a
fragment its message must contain and the HTTP status the server answers."""
from __future__ import annotations

import json

import numpy as np
import pytest
from serve_fixtures import build_fake_model, encode_image, image_files, synthetic_images, wait_app_ready

from occflownet.contract import (MAX_CALIBRATION_BYTES, MAX_CALIBRATION_DEPTH, CalibrationError, load_calibration,
                                 parse_calibration_json, validate_calibration)
from occflownet.occ3d import CAMERAS
from occflownet.rig import default_rig

DEEP = 2000


def _with(path: tuple, value):
    """A fault that sets the element at ``path`` (keys and indices from the top) to ``value``."""
    def make(base: dict) -> str:
        calib = json.loads(json.dumps(base))
        node = calib
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
        return json.dumps(calib)
    return make


def _nested(base: dict) -> str:
    """A valid calibration with an extra key holding arrays nested DEEP levels."""
    return json.dumps(base)[:-1] + ', "extra": ' + "[" * DEEP + "]" * DEEP + "}"


def _oversize(base: dict) -> str:
    """A valid calibration padded with spaces to one byte over the limit."""
    text = json.dumps(base)
    return text + " " * (MAX_CALIBRATION_BYTES + 1 - len(text))


# name: (make(base calibration) -> JSON text, fragment of the message, the server's status)
FAULTS = {
    "nested_2000_deep": (_nested, f"nested deeper than {MAX_CALIBRATION_DEPTH} levels", 400),
    "fx_1e308": (_with(("cameras", "CAM_FRONT", "intrinsic", 0, 0), 1e308),
                 "CAM_FRONT intrinsic[0][0] must be finite in float32, got 1e+308", 400),
    "translation_1e308": (_with(("cameras", "CAM_BACK", "cam2ego", 1, 3), -1e308),
                          "CAM_BACK cam2ego[1][3] must be finite in float32, got -1e+308", 400),
    "boolean": (_with(("cameras", "CAM_FRONT_LEFT", "intrinsic", 2, 2), True),
                "CAM_FRONT_LEFT intrinsic[2][2] must be a JSON number, got true", 400),
    "string_number": (_with(("cameras", "CAM_FRONT", "intrinsic", 0, 0), "1266.4"),
                      'CAM_FRONT intrinsic[0][0] must be a JSON number, got "1266.4"', 400),
    "string_translation": (_with(("cameras", "CAM_BACK_RIGHT", "cam2ego", 2, 3), "1.5"),
                           'CAM_BACK_RIGHT cam2ego[2][3] must be a JSON number, got "1.5"', 400),
    "image_size_boolean": (_with(("image_size", 1), True), "calibration image_size[1] must be a JSON number, got true",
                           400),
    "image_size_string": (_with(("cameras", "CAM_BACK", "image_size"), ["1600", "900"]),
                          'CAM_BACK image_size[0] must be a JSON number, got "1600"', 400),
    "image_size_1e9": (_with(("image_size", 0), 1e9), "calibration image_size must be two integers from 1 to 65535, "
                       "got [1000000000.0, ", 400),
    "oversize": (_oversize, f"bytes, over the limit of {MAX_CALIBRATION_BYTES} bytes", 413),
}


def fault_text(name: str, base: dict) -> str:
    return FAULTS[name][0](base)


# ----------------------------------------------------------------------------------------------- the contract
@pytest.mark.parametrize("name", sorted(FAULTS))
def test_the_contract_refuses_each_fault(name):
    text = fault_text(name, default_rig(1600, 900))
    with pytest.raises(CalibrationError) as info:
        validate_calibration(parse_calibration_json(text, "calibration"))
    assert FAULTS[name][1] in str(info.value), str(info.value)


@pytest.mark.parametrize("name", sorted(FAULTS))
def test_load_calibration_refuses_each_fault_naming_the_file(name, tmp_path):
    path = tmp_path / "calib.json"
    path.write_text(fault_text(name, default_rig(1600, 900)))
    with pytest.raises(CalibrationError) as info:
        load_calibration(path)
    assert str(info.value).startswith(str(path)) and FAULTS[name][1] in str(info.value), str(info.value)


def test_the_limits_are_exact():
    """Nesting of MAX_CALIBRATION_DEPTH levels and MAX_CALIBRATION_BYTES bytes are accepted, one more refused;
    brackets inside strings are not nesting."""
    base = default_rig(480, 270)
    for extra, ok in ((MAX_CALIBRATION_DEPTH - 1, True), (MAX_CALIBRATION_DEPTH, False)):
        text = json.dumps(base)[:-1] + ', "extra": ' + "[" * extra + "]" * extra + "}"   # the top object is level 1
        if ok:
            validate_calibration(parse_calibration_json(text))
        else:
            with pytest.raises(CalibrationError, match=f"nested deeper than {MAX_CALIBRATION_DEPTH} levels"):
                parse_calibration_json(text)
    quoted = json.dumps(base)[:-1] + ', "extra": ' + json.dumps("[{" * 5000 + '\\"' + "]" * 3) + "}"
    validate_calibration(parse_calibration_json(quoted))
    text = json.dumps(base)
    exact = text + " " * (MAX_CALIBRATION_BYTES - len(text))
    validate_calibration(parse_calibration_json(exact.encode()))
    with pytest.raises(CalibrationError, match="over the limit"):
        parse_calibration_json((exact + " ").encode())
    multibyte = text[:-1] + ', "name": "' + "é" * ((MAX_CALIBRATION_BYTES - len(text)) // 2) + '"}'
    assert len(multibyte) < MAX_CALIBRATION_BYTES < len(multibyte.encode())   # the limit counts UTF-8 bytes
    with pytest.raises(CalibrationError, match="over the limit"):
        parse_calibration_json(multibyte)


# ----------------------------------------------------------------------------------------------- predict
@pytest.fixture(scope="module")
def predict_setup(tmp_path_factory):
    """(fake contract-v1 model, a folder of six 96x54 PNGs) for `occflownet predict --model`."""
    root = tmp_path_factory.mktemp("predict-faults")
    model = build_fake_model(root / "fake.onnx")
    folder = root / "images"
    folder.mkdir()
    for cam, rgb in zip(CAMERAS, synthetic_images((96, 54))):
        (folder / f"{cam}.png").write_bytes(encode_image(rgb))
    return model, folder


@pytest.mark.parametrize("name", sorted(FAULTS))
def test_predict_refuses_each_fault_in_one_line(name, predict_setup, tmp_path, capsys):
    from occflownet.cli import main

    model, folder = predict_setup
    calib = tmp_path / "calib.json"
    calib.write_text(fault_text(name, default_rig(96, 54)))
    out = tmp_path / "grid.npz"
    rc = main(["predict", "--model", str(model), "--images", str(folder), "--calib", str(calib), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and not out.exists(), err
    assert err.count("\n") == 1 and err.startswith(f"occflownet predict: {calib}") and FAULTS[name][1] in err, err


def test_predict_accepts_the_valid_calibration(predict_setup, tmp_path, capsys):
    from occflownet.cli import main

    model, folder = predict_setup
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(default_rig(96, 54)))
    rc = main(["predict", "--model", str(model), "--images", str(folder), "--calib", str(calib),
               "--out", str(tmp_path / "grid.npz")])
    assert rc == 0, capsys.readouterr().err
    assert np.load(tmp_path / "grid.npz")["occupancy"].shape == (200, 200, 16)


# ----------------------------------------------------------------------------------------------- the server
@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from starlette.testclient import TestClient

    from occflownet.serve.app import create_app
    from occflownet.serve.settings import ServeSettings

    model = build_fake_model(tmp_path_factory.mktemp("serve-faults") / "fake.onnx")
    app = create_app(ServeSettings(model_path=str(model), max_body_bytes=4_000_000, max_image_pixels=200_000))
    with TestClient(app) as c:
        wait_app_ready(c)
        yield c


SERVER_IMAGES = image_files(synthetic_images((96, 54)))


def _post(client, calibration: str):
    return client.post("/v1/occupancy", files=SERVER_IMAGES | {"calibration": ("calib.json", calibration.encode(),
                                                                               "application/json")})


@pytest.mark.parametrize("name", sorted(FAULTS))
def test_the_server_refuses_each_fault_with_a_4xx(name, client):
    r = _post(client, fault_text(name, default_rig(96, 54)))
    assert r.status_code == FAULTS[name][2], (r.status_code, r.text[:500])
    if r.status_code == 400:
        err = r.json()["error"]
        assert err["code"] == "bad_calibration" and FAULTS[name][1] in err["message"], err
    assert _post(client, json.dumps(default_rig(96, 54))).status_code == 200     # and serves the next one


def test_the_server_takes_a_calibration_of_exactly_the_limit(client):
    text = json.dumps(default_rig(96, 54))
    assert _post(client, text + " " * (MAX_CALIBRATION_BYTES - len(text))).status_code == 200
    assert _post(client, text + " " * (MAX_CALIBRATION_BYTES + 1 - len(text))).status_code == 413

