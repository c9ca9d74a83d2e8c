"""occflownet.contract: the one torch-free definition of contract v1 (tensors, metadata, calibration, rescaling)."""
import json
import subprocess
import sys

import numpy as np
import pytest

from occflownet import contract
from occflownet.occ3d import CAMERAS, CLASS_COLORS, CLASS_NAMES, GRID
from occflownet.contract import (CalibrationError, ContractError, MissingCalibrationField, calibration_arrays,
                                 calibration_json,
                                 check_signature, parse_metadata, rescale_intrinsics, scale_intrinsics,
                                 validate_calibration)
from occflownet.rig import default_rig


def test_importing_the_contract_pulls_in_neither_torch_nor_onnx_nor_onnxruntime():
    code = ("import sys, occflownet.contract, occflownet.predict, occflownet.pictures; "
            "bad = [m for m in ('torch', 'onnx', 'onnxruntime') if m in sys.modules]; assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


# ---------------------------------------------------------------- rescaling (pixel-centre rule)

K0 = np.array([[1266.0, 0.3, 816.3], [0.0, 1260.5, 491.2], [0.0, 0.0, 1.0]])


def test_scale_intrinsics_known_answer():
    K = scale_intrinsics(K0, 0.5, 0.5)
    np.testing.assert_allclose(K, [[633.0, 0.15, (816.3 + 0.5) * 0.5 - 0.5], [0.0, 630.25, (491.2 + 0.5) * 0.5 - 0.5],
                                   [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("sx,sy", [(0.5, 0.5), (0.3, 0.3), (2.0, 2.0), (800 / 1600, 450 / 900), (0.61, 0.6)])
def test_rescaling_round_trips_exactly(sx, sy):
    there = scale_intrinsics(K0, sx, sy)
    np.testing.assert_allclose(scale_intrinsics(there, 1 / sx, 1 / sy), K0, rtol=1e-12, atol=1e-9)
    # composition: resizing twice is one resize by the product
    np.testing.assert_allclose(scale_intrinsics(there, 1.7, 1.7), scale_intrinsics(K0, 1.7 * sx, 1.7 * sy),
                               rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("size", [(800, 450), (533, 300), (1920, 1080)])
def test_rescaled_intrinsics_follow_a_cv2_resized_blob(size):
    """Known answer: a Gaussian blob drawn at the projection of a 3D point in a 1600x900 image lands, after
    cv2.resize (INTER_AREA shrinking, INTER_LINEAR enlarging; half-pixel centres), where the rescaled K projects it."""
    import cv2

    W, H = 1600, 900
    point = np.array([0.7, -0.4, 9.0])
    uv = (K0 @ point)[:2] / point[2]
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    blob = 250.0 * np.exp(-((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2) / (2 * 14.0 ** 2))
    method = cv2.INTER_AREA if size[0] < W else cv2.INTER_LINEAR
    small = cv2.resize(blob.astype(np.float32), size, interpolation=method).astype(np.float64)
    ys, xs = np.mgrid[0:size[1], 0:size[0]]
    got = np.array([(small * xs).sum() / small.sum(), (small * ys).sum() / small.sum()])
    K = rescale_intrinsics(K0, (W, H), size)
    want = (K @ point)[:2] / point[2]
    assert np.abs(got - want).max() < 0.02, (got, want)
    # the other rule (K' = diag(sx, sy, 1)·K) is off by (s − 1)/2 pixels, e.g. a quarter pixel at half size
    naive = (np.diag([size[0] / W, size[1] / H, 1.0]) @ K0 @ point)[:2] / point[2]
    assert np.abs(naive - want).max() == pytest.approx(abs(size[0] / W - 1) / 2, rel=1e-6)


def test_a_different_aspect_ratio_is_refused_naming_the_camera():
    with pytest.raises(CalibrationError, match=r"CAM_BACK: image is 1000x1000 but the calibration is for 1600x900 "
                                               r"\(aspect ratio 1.000 vs 1.778\)"):
        rescale_intrinsics(K0, (1600, 900), (1000, 1000), camera="CAM_BACK")
    np.testing.assert_array_equal(rescale_intrinsics(K0, None, (1000, 1000)), K0)       # no size: as they come
    np.testing.assert_array_equal(rescale_intrinsics(K0, (1600, 900), (1605, 900)),      # within 1 %: rescaled
                                  scale_intrinsics(K0, 1605 / 1600, 1))


def test_calibration_arrays_for_an_image_size_and_per_camera_sizes():
    calib = default_rig(480, 270)
    K, T = calibration_arrays(calib, 960, 540)
    assert K.shape == (6, 3, 3) and T.shape == (6, 4, 4) and K.dtype == T.dtype == np.float32
    np.testing.assert_allclose(K, scale_intrinsics(np.array([c["intrinsic"] for c in calib["cameras"].values()]),
                                                   2.0, 2.0), rtol=1e-6)
    np.testing.assert_allclose(calibration_arrays(calib)[0], calibration_arrays(calib, 480, 270)[0])
    calib["cameras"]["CAM_BACK"]["image_size"] = [960, 540]                 # this camera's K is for 960x540
    calib["cameras"]["CAM_BACK"]["intrinsic"] = scale_intrinsics(np.array(
        calib["cameras"]["CAM_BACK"]["intrinsic"]), 2.0, 2.0).tolist()
    K2, _ = calibration_arrays(calib, 480, 270)
    np.testing.assert_allclose(K2, calibration_arrays(default_rig(480, 270))[0], rtol=1e-6, atol=1e-5)
    cal = validate_calibration(calib)
    assert cal.image_sizes == ((480, 270),) * 3 + ((960, 540),) + ((480, 270),) * 2


def test_arrays_for_rescales_once_from_the_calibration_to_the_tensor():
    """Calibration size → stored size → 1/n (reduced-scale JPEG) → the size the decoded image is resized to: one
    rescale in float64 (pixel-centre rule), the composition of the three steps, exactly unchanged where a step
    is the identity; the tensor step checks no aspect ratio (the resize is the caller's own, known exactly)."""
    calib = default_rig(1600, 900)
    cal = validate_calibration(calib)
    K0s = np.array([c["intrinsic"] for c in calib["cameras"].values()])
    sizes = [(1600, 900), (800, 450), (1600, 900), (3200, 1800), (1601, 901), (1600, 900)]
    reductions = [2, 1, 1, 4, 2, 8]
    K, T = cal.arrays_for(sizes, reductions=reductions, size=(800, 450))
    assert K.dtype == T.dtype == np.float32
    for i, ((w, h), n) in enumerate(zip(sizes, reductions)):
        decoded = (-(-w // n), -(-h // n))
        step = scale_intrinsics(scale_intrinsics(rescale_intrinsics(K0s[i], (1600, 900), (w, h)), 1 / n, 1 / n),
                                800 / decoded[0], 450 / decoded[1])
        np.testing.assert_allclose(K[i], step, rtol=1e-6)
    np.testing.assert_array_equal(K[0], calibration_arrays(calib, 800, 450)[0][0])        # 1/2 == 800/1600
    np.testing.assert_array_equal(cal.arrays_for(sizes[:1] * 6, reductions=[2] * 6, size=(800, 450))[0],
                                  cal.arrays_for(sizes[:1] * 6, reductions=[2] * 6)[0])  # no third step
    K_odd, _ = cal.arrays_for([(1601, 901)] * 6, reductions=[2] * 6, size=(900, 900))     # tensor: any aspect
    assert K_odd[0, 0, 0] == pytest.approx(K0s[0, 0, 0] * 1601 / 1600 / 2 * 900 / 801, rel=1e-6)


def test_calibration_from_a_datasets_arrays_is_taken_as_it_comes():
    K = np.stack([np.array([[100.0 + i, 0, 40], [0, 100.0 + i, 30], [0, 0, 1]]) for i in range(6)]).astype(np.float32)
    T = np.stack([np.eye(4)] * 6)
    cal = contract.Calibration.from_arrays(K, T)
    assert cal.cameras == CAMERAS and cal.image_sizes == (None,) * 6
    K2, T2 = cal.arrays_for([(80, 60)] * 6)
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(T2, T.astype(np.float32))


def test_calibration_json_is_what_calibration_arrays_reads_back():
    K = np.stack([np.array([[100.0 + i, 0, 40], [0, 100.0 + i, 30], [0, 0, 1]]) for i in range(6)])
    T = np.stack([np.eye(4)] * 6)
    T[:, 0, 3] = np.arange(6)
    calib = calibration_json(K, T, (80, 60))
    assert list(calib["cameras"]) == list(CAMERAS) and calib["image_size"] == [80, 60]
    assert calib["cameras"]["CAM_FRONT_RIGHT"]["intrinsic"][0][0] == 101.0
    K2, T2 = calibration_arrays(json.loads(json.dumps(calib)), 160, 120)
    np.testing.assert_allclose(K2, scale_intrinsics(K, 2.0, 2.0), rtol=1e-6)
    np.testing.assert_array_equal(T2[:, 0, 3], np.arange(6))
    assert "image_size" not in calibration_json(K, T)
    with pytest.raises(ValueError):                                       # one matrix per camera, no fewer
        calibration_json(K[:5], T[:5])


# ---------------------------------------------------------------- validation

@pytest.mark.parametrize("mutate, message", [
    (lambda c: c["cameras"]["CAM_FRONT"]["intrinsic"].__setitem__(2, [0, 0, 2]), "CAM_FRONT intrinsic last row"),
    (lambda c: c["cameras"]["CAM_FRONT"]["intrinsic"][0].__setitem__(0, -5.0), "CAM_FRONT intrinsic focal"),
    (lambda c: c["cameras"]["CAM_BACK"]["cam2ego"].__setitem__(3, [0, 0, 1, 1]), "CAM_BACK cam2ego last row"),
    (lambda c: c["cameras"]["CAM_BACK"]["cam2ego"][0].__setitem__(0, 1.1), "CAM_BACK cam2ego rotation"),
    (lambda c: c["cameras"]["CAM_BACK_LEFT"]["cam2ego"][0].__setitem__(1, float("nan")),
     r"CAM_BACK_LEFT cam2ego\[0\]\[1\] must be finite in float32, got nan"),
    (lambda c: c.__setitem__("image_size", [480]), "calibration image_size must be"),
    (lambda c: c["cameras"]["CAM_BACK"].__setitem__("image_size", [0, 5]), "CAM_BACK image_size must be"),
])
def test_bad_calibrations_name_camera_and_field(mutate, message):
    calib = default_rig(480, 270)
    mutate(calib)
    with pytest.raises(CalibrationError, match=message):
        validate_calibration(calib)


def test_numbers_must_round_to_a_finite_float32():
    """FLOAT32_LIMIT is exact: the largest double below it casts to float32's largest value, the limit itself to
    inf; a calibration entry at the one is accepted (and reaches the model finite), at the other refused."""
    below = np.nextafter(contract.FLOAT32_LIMIT, 0.0)
    with np.errstate(over="ignore"):
        assert np.float32(below) == np.finfo(np.float32).max and np.isinf(np.float32(contract.FLOAT32_LIMIT))
    calib = default_rig(480, 270)
    calib["cameras"]["CAM_FRONT_LEFT"]["cam2ego"][2][3] = float(below)
    _, T = calibration_arrays(calib)
    assert np.isfinite(T).all() and T[2, 2, 3] == np.finfo(np.float32).max
    calib["cameras"]["CAM_FRONT_LEFT"]["cam2ego"][2][3] = -contract.FLOAT32_LIMIT
    with pytest.raises(CalibrationError, match=r"CAM_FRONT_LEFT cam2ego\[2\]\[3\] must be finite in float32, "
                                               r"got -3.402823567797\d*e\+38"):
        validate_calibration(calib)
    calib["cameras"]["CAM_FRONT_LEFT"]["cam2ego"][2][3] = 10 ** 400            # an integer beyond any double
    with pytest.raises(CalibrationError, match=r"cam2ego\[2\]\[3\] must be finite in float32"):
        validate_calibration(calib)


def test_intrinsics_rescaled_beyond_float32_are_refused():
    """fx finite in float32 at the calibration's size, beyond it once scaled to the image: refused naming the
    camera, never inf in the model's input."""
    calib = default_rig(480, 270)
    calib["cameras"]["CAM_BACK"]["intrinsic"][0][0] = 3e38
    calibration_arrays(calib, 480, 270)
    with pytest.raises(CalibrationError, match="CAM_BACK intrinsic rescaled for a 960x540 image is not finite"):
        calibration_arrays(calib, 960, 540)


def test_python_callers_may_pass_numpy_numbers_but_not_booleans():
    calib = default_rig(480, 270)
    K = np.array(calib["cameras"]["CAM_FRONT"]["intrinsic"], np.float32)
    calib["cameras"]["CAM_FRONT"]["intrinsic"] = K                             # an array of numbers
    calib["cameras"]["CAM_FRONT"]["image_size"] = [np.int64(480), np.int32(270)]
    np.testing.assert_array_equal(validate_calibration(calib).intrinsics[0], K)
    calib["cameras"]["CAM_FRONT"]["intrinsic"] = np.eye(3, dtype=bool)
    with pytest.raises(CalibrationError, match=r"CAM_FRONT intrinsic\[0\]\[0\] must be a JSON number, got true"):
        validate_calibration(calib)
    calib["cameras"]["CAM_FRONT"]["intrinsic"] = [[1.0, 0, 1], [0, 1.0, 1], [0, 0, None]]
    with pytest.raises(CalibrationError, match=r"intrinsic\[2\]\[2\] must be a JSON number, got null"):
        validate_calibration(calib)
    calib["cameras"]["CAM_FRONT"]["intrinsic"] = "[[1, 0, 0], [0, 1, 0], [0, 0, 1]]"
    with pytest.raises(CalibrationError, match="CAM_FRONT intrinsic must be a 3x3 array of numbers"):
        validate_calibration(calib)


def test_a_mirrored_camera_is_not_a_rotation():
    calib = default_rig(480, 270)
    T = np.array(calib["cameras"]["CAM_FRONT"]["cam2ego"])
    T[:3, 0] *= -1                                                         # orthonormal, det −1
    calib["cameras"]["CAM_FRONT"]["cam2ego"] = T.tolist()
    with pytest.raises(CalibrationError, match="CAM_FRONT cam2ego rotation is not a proper rotation"):
        validate_calibration(calib)


def test_missing_fields_are_key_errors_too():
    calib = default_rig(480, 270)
    del calib["cameras"]["CAM_FRONT"]["intrinsic"]
    with pytest.raises(MissingCalibrationField) as info:
        validate_calibration(calib)
    assert isinstance(info.value, KeyError) and isinstance(info.value, ValueError)
    assert str(info.value) == "calibration of CAM_FRONT lacks 'intrinsic'"


def test_load_calibration_names_the_file(tmp_path):
    path = tmp_path / "calib.json"
    path.write_text("{broken")
    with pytest.raises(CalibrationError, match="calib.json is not valid UTF-8 JSON"):
        contract.load_calibration(path)
    calib = default_rig(480, 270)
    calib["cameras"]["CAM_FRONT"]["cam2ego"][3] = [1, 0, 0, 1]
    path.write_text(json.dumps(calib))
    with pytest.raises(CalibrationError, match=r"calib.json: CAM_FRONT cam2ego last row"):
        contract.load_calibration(path)
    with pytest.raises(FileNotFoundError, match="calibration file not found"):
        contract.load_calibration(tmp_path / "nope.json")


# ---------------------------------------------------------------- tensors and metadata

GOOD_IN = [("images", "uint8", [None, 6, None, None, 3]), ("intrinsics", "float32", [None, 6, 3, 3]),
           ("cam2ego", "float32", [None, 6, 4, 4])]
GOOD_OUT = [("occupancy", "uint8", [None, 200, 200, 16]), ("density", "float32", [None, 200, 200, 16])]


def test_check_signature():
    check_signature(GOOD_IN, GOOD_OUT, "m.onnx", exact=True)
    ort_style = [("images", "tensor(uint8)", ["batch", 6, 900, 1600, 3])] + GOOD_IN[1:]
    check_signature(ort_style, GOOD_OUT, "m.onnx")                          # a pinned image size is allowed
    with pytest.raises(ContractError, match="m.onnx: input 'images' is tensor\\(uint8\\) .* needs uint8"):
        check_signature(ort_style, GOOD_OUT, "m.onnx", exact=True)
    with pytest.raises(ContractError, match="m.onnx: input 'intrinsics' is float64"):
        check_signature([GOOD_IN[0], ("intrinsics", "float64", [None, 6, 3, 3]), GOOD_IN[2]], GOOD_OUT, "m.onnx")
    with pytest.raises(ContractError, match="m.onnx: model has no output 'density'"):
        check_signature(GOOD_IN, GOOD_OUT[:1], "m.onnx")
    with pytest.raises(ContractError, match="cam2ego"):
        check_signature(GOOD_IN[:2] + [("cam2ego", "float32", [None, 5, 4, 4])], GOOD_OUT, "m.onnx")
    assert contract.INPUT_NAMES == ("images", "intrinsics", "cam2ego")
    assert [s.onnx_elem_type for s in contract.OUTPUTS] == [2, 1]


def _metadata():
    return {"classes": list(CLASS_NAMES), "free_index": 17, "grid": GRID.to_dict(), "cameras": list(CAMERAS),
            "class_colors": CLASS_COLORS.astype(int).tolist(), "threshold": 0.3, "input_size": [160, 288],
            "preset": "tiny", "default_calibration": default_rig(480, 270), "occflownet_version": "0.1.0",
            "onnx_contract": "v1", "foreign": "plain text"}


def test_metadata_round_trip_and_errors():
    props = contract.encode_metadata(_metadata())
    props["foreign"] = "not json"                                          # other writers' keys survive as text
    md = parse_metadata(props, "m.onnx")
    assert md.cameras == CAMERAS and md.threshold == 0.3 and md.input_size == (160, 288) and md.preset == "tiny"
    assert md.grid_shape == GRID.shape and md.class_colors.dtype == np.uint8 and md.raw["foreign"] == "not json"
    assert set(contract.METADATA_KEYS) <= set(props)
    bad_calib = _metadata()
    bad_calib["default_calibration"]["cameras"]["CAM_BACK"]["intrinsic"] = [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    for meta, message in ((_metadata() | {"onnx_contract": "v2"}, "onnx_contract is 'v2'"),
                          (_metadata() | {"free_index": 18}, "free_index 18"),
                          (_metadata() | {"cameras": CAMERAS[:5]}, "cameras must be 6 distinct names"),
                          (bad_calib, "default_calibration: CAM_BACK intrinsic is singular")):
        with pytest.raises(ContractError, match=f"m.onnx: invalid model metadata: {message}"):
            parse_metadata(contract.encode_metadata(meta), "m.onnx")
    overflow = _metadata()
    overflow["default_calibration"]["cameras"]["CAM_FRONT"]["intrinsic"][0][0] = 1e308
    with pytest.raises(ContractError, match=r"m.onnx: invalid model metadata: default_calibration: CAM_FRONT "
                                            r"intrinsic\[0\]\[0\] must be finite in float32"):
        parse_metadata(contract.encode_metadata(overflow), "m.onnx")
    with pytest.raises(ContractError, match="m.onnx: model metadata lacks threshold"):
        parse_metadata({k: v for k, v in props.items() if k != "threshold"}, "m.onnx")


def test_metadata_nested_deeper_than_the_limit_is_never_decoded():
    """A metadata value nested 2,000 deep stays text (no recursion); as the default calibration it is refused with
    the calibration's nesting message."""
    deep = "[" * 2000 + "]" * 2000
    props = contract.encode_metadata(_metadata()) | {"foreign": deep}
    assert parse_metadata(props, "m.onnx").raw["foreign"] == deep
    calib = json.dumps(default_rig(480, 270))
    props["default_calibration"] = calib[:-1] + f', "extra": {deep}}}'
    with pytest.raises(ContractError, match="m.onnx: invalid model metadata: default_calibration is nested deeper "
                                            f"than {contract.MAX_CALIBRATION_DEPTH} levels"):
        parse_metadata(props, "m.onnx")


def test_sessions_refuse_a_model_that_breaks_the_contract(tmp_path):
    """create_session (predict, eval --model, parity, serve) checks signature and metadata, naming the file."""
    import onnx
    from onnx import TensorProto, helper

    from occflownet.contract import create_session

    graph = helper.make_graph([helper.make_node("Identity", ["images"], ["occupancy"])], "g",
                              [helper.make_tensor_value_info("images", TensorProto.UINT8, [1, 6, 4, 4, 3])],
                              [helper.make_tensor_value_info("occupancy", TensorProto.UINT8, [1, 6, 4, 4, 3])])
    path = tmp_path / "not-v1.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=10), str(path))
    with pytest.raises(ContractError, match="not-v1.onnx: model has no input 'intrinsics'"):
        create_session(path)
    assert create_session(path, check_contract=False).get_inputs()[0].name == "images"


# ---------------------------------------------------------------- images of different sizes in one frame

def test_common_size_is_the_most_common_ties_to_the_earliest_camera():
    from occflownet.contract import common_size

    assert common_size([(800, 450), (1600, 900), (800, 450), (800, 450), (1600, 900), (1600, 900)]) == (800, 450)
    assert common_size([(1600, 900), (800, 450), (800, 450), (1600, 900), (640, 360), (800, 450)]) == (800, 450)
    assert common_size([(640, 360), (800, 450), (800, 450), (640, 360), (1, 1), (2, 2)]) == (640, 360)


def test_resize_rgb_copies_shrinks_by_area_and_enlarges_linearly():
    import cv2

    from occflownet.contract import resize_rgb

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    out = np.zeros((30, 40, 3), np.uint8)
    assert resize_rgb(rgb, (40, 30), out) is out and np.array_equal(out, rgb)        # same size: the pixels
    np.testing.assert_array_equal(resize_rgb(rgb, (16, 12)),                          # 2.5x down: area average
                                  cv2.resize(rgb, (16, 12), interpolation=cv2.INTER_AREA))
    big = resize_rgb(rgb, (100, 75))
    np.testing.assert_array_equal(big, cv2.resize(rgb, (100, 75), interpolation=cv2.INTER_LINEAR))
    assert not np.array_equal(big, cv2.resize(rgb, (100, 75), interpolation=cv2.INTER_AREA))
    with pytest.raises(ValueError, match="out has shape"):
        resize_rgb(rgb, (20, 15), np.zeros((15, 21, 3), np.uint8))


def test_decoded_images_are_rgb_contiguous_and_writable():
    """decode_rgb gives RGB (a red / green / blue pixel of a lossless PNG reads back as such), as a C-contiguous,
    writable uint8 array of its own, also from a JPEG at a reduced scale."""
    import cv2

    rgb = np.zeros((4, 6, 3), dtype=np.uint8)
    rgb[0, 0], rgb[1, 2], rgb[3, 5] = (255, 0, 0), (0, 255, 0), (0, 0, 255)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))        # OpenCV writes BGR
    out = contract.decode_rgb(png.tobytes())
    assert ok and np.array_equal(out, rgb)
    assert out.dtype == np.uint8 and out.flags["C_CONTIGUOUS"] and out.flags["WRITEABLE"] and out.base is None
    blue = np.zeros((64, 96, 3), dtype=np.uint8)
    blue[..., 2] = 200
    ok, jpeg = cv2.imencode(".jpg", np.ascontiguousarray(blue[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
    small = contract.decode_rgb(jpeg.tobytes(), 2)
    assert small.shape == (32, 48, 3) and small.flags["C_CONTIGUOUS"]
    assert np.abs(small.astype(int) - (0, 0, 200)).max() <= 3
