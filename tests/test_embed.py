"""embed/: the C++ runner library, the occflownet-run program and the C demo, built by scripts/setup-embed (Debian
packages, onnxruntime headers through a scratch apt, CMake) and checked against Python onnxruntime on the real
nuScenes frame: the same decoded pixels, intrinsics and grids (occupancy on every voxel, density within 1e-6), clear
errors for bad inputs (exit status 1, message naming the problem), and clean AddressSanitizer runs.

A failed set-up or build fails the tests (never a skip); only the real frame's absence skips, as elsewhere."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from exported_models import FRAME, exported_tiny, frame_available, trained_tiny_checkpoint, workdir
from test_calibration_faults import FAULTS

REPO = Path(__file__).resolve().parents[1]
BUILD = REPO / "embed" / "build"
SETUP_TIMEOUT = 1800

needs_frame = pytest.mark.skipif(not frame_available(), reason=f"real frame not found at {FRAME}")


# ----------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="session")
def embed_build() -> dict[str, Path]:
    """scripts/setup-embed (idempotent, cached in embed/build/): Release and ASan builds of every target."""
    proc = subprocess.run(["bash", str(REPO / "scripts" / "setup-embed")], capture_output=True, text=True,
                          timeout=SETUP_TIMEOUT, env=_env(PYTHON=sys.executable))
    assert proc.returncode == 0, f"scripts/setup-embed failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}"
    paths = {"run": BUILD / "release" / "occflownet-run", "c_demo": BUILD / "release" / "occflownet-c-demo",
             "run_asan": BUILD / "asan" / "occflownet-run", "c_demo_asan": BUILD / "asan" / "occflownet-c-demo"}
    for name, path in paths.items():
        assert path.is_file(), f"setup-embed did not build {name} ({path})"
    return paths


@pytest.fixture(scope="session")
def random_model() -> Path:
    return exported_tiny()[0]


@pytest.fixture(scope="session")
def trained_model() -> Path:
    """The briefly trained tiny checkpoint (3D labels, about 1 % occupied voxels on the real frame), exported."""
    from occflownet.export.onnx_export import export_model
    from occflownet.model import load_checkpoint

    out = workdir() / "trained-tiny.onnx"
    if not out.is_file():
        model, cfg, _ = load_checkpoint(trained_tiny_checkpoint())
        export_model(model.eval(), cfg, out)
    return out


def _env(**extra) -> dict:
    import os

    env = dict(os.environ)
    env.update({"ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0:exitcode=86",
                "LSAN_OPTIONS": "exitcode=87", "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1:exitcode=88"})
    env.update(extra)
    return env


def run_program(binary: Path, *args, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary), *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          env=_env())


def assert_no_sanitizer_report(proc: subprocess.CompletedProcess) -> None:
    assert "Sanitizer" not in proc.stderr and "runtime error:" not in proc.stderr, proc.stderr[-6000:]
    assert proc.returncode not in (86, 87, 88), proc.stderr[-6000:]


# ----------------------------------------------------------------------------------------------- Python side
def python_calibration(calib_path: Path, width: int, height: int, reduction: int = 1):
    """(intrinsics float32 [6, 3, 3], cam2ego [6, 4, 4]) by the Python rule (``occflownet.contract``) for images of
    width x height as stored, decoded at 1/``reduction``."""
    from occflownet.contract import calibration_arrays

    return calibration_arrays(json.loads(Path(calib_path).read_text()), width, height, reduction=reduction)


def python_frame(model: Path, folder: Path):
    """The frame of ``folder`` as Python's inference paths decode it for ``model`` (JPEGs at reduced scale)."""
    from occflownet.contract import check_session, create_session
    from occflownet.predict import load_frame

    return load_frame(folder, check_session(create_session(model), str(model)).input_size)


def python_reference(model: Path, folder: Path, calib_path: Path):
    """What Python onnxruntime gives on ``folder`` decoded as ``predict`` decodes it: (images, intrinsics,
    occupancy, density)."""
    from occflownet.runtime import OnnxPredictor

    frame = python_frame(model, folder)
    inputs = frame.inputs(json.loads(Path(calib_path).read_text()))
    occupancy, density = OnnxPredictor.open(model)(inputs)
    return frame.images, inputs.intrinsics[0], occupancy[0], density[0]


def cpp_run(binary: Path, model: Path, folder: Path, calib: Path | None, out: Path, runs: int = 1):
    """occflownet-run with every dump; returns (proc, outputs dict of arrays)."""
    out.mkdir(parents=True, exist_ok=True)
    args = ["--model", model, "--images", folder, "--out", out / "grid.npy", "--density-out", out / "density.npy",
            "--intrinsics-out", out / "K.npy", "--images-out", out / "images.npy", "--runs", runs]
    if calib is not None:
        args += ["--calib", calib]
    proc = run_program(binary, *args)
    assert proc.returncode == 0, proc.stderr[-6000:]
    arrays = {name: np.load(out / f"{name}.npy") for name in ("grid", "density", "K", "images")}
    return proc, arrays


def printed_counts(stdout: str) -> dict[int, int]:
    return {int(m[1]): int(m[3]) for m in re.finditer(r"^\s+(\d+) (\S+)\s+(\d+)$", stdout, re.M)}


def frame_copy(tmp_path: Path, size: tuple[int, int] | None = None, suffix: str = ".jpg") -> Path:
    """The real frame's six images in a scratch folder: copied, or resized to ``size`` (w, h) with INTER_AREA and
    written losslessly as PNG (suffix ".png")."""
    import cv2

    folder = tmp_path / "frame"
    folder.mkdir()
    for src in sorted(FRAME.glob("CAM_*.jpg")):
        if size is None:
            shutil.copy(src, folder / src.name)
        else:
            im = cv2.resize(cv2.imread(str(src)), size, interpolation=cv2.INTER_AREA)
            assert cv2.imwrite(str(folder / (src.stem + suffix)), im)
    return folder


# ----------------------------------------------------------------------------------------------- build
def test_clean_build_from_scratch_without_warnings(embed_build, tmp_path):
    """A fresh CMake build directory, warnings as errors, against the onnxruntime set up by setup-embed."""
    ort = BUILD / "ort"
    cfg = subprocess.run(["cmake", "-S", REPO / "embed", "-B", tmp_path / "b", f"-DONNXRUNTIME_ROOT={ort}",
                          "-DCMAKE_BUILD_TYPE=Release", "-DOCCFLOWNET_WERROR=ON"],
                         capture_output=True, text=True, timeout=300)
    assert cfg.returncode == 0, cfg.stdout + cfg.stderr
    build = subprocess.run(["cmake", "--build", tmp_path / "b", "-j", "2"], capture_output=True, text=True,
                           timeout=900)
    assert build.returncode == 0, build.stdout[-6000:] + build.stderr[-6000:]
    proc = run_program(tmp_path / "b" / "occflownet-run", "--help")
    assert proc.returncode == 0 and "--model" in proc.stdout


# ----------------------------------------------------------------------------------------------- equality
@needs_frame
def test_decoded_pixels_and_intrinsics_equal_python(embed_build, random_model, tmp_path):
    """libjpeg-turbo's DCT scaling here and OpenCV's IMREAD_REDUCED_COLOR_4 in Python give the same RGB bytes for
    the real frame at quarter scale (tiny: n = 4), and the calibration gives the same float32 intrinsics (1/4 rule)."""
    _, got = cpp_run(embed_build["run"], random_model, FRAME, FRAME / "calib.json", tmp_path)
    frame = python_frame(random_model, FRAME)
    assert frame.reductions == (4,) * 6 and frame.sizes == ((1600, 900),) * 6
    assert got["images"].shape == frame.images.shape == (6, 225, 400, 3)
    assert np.array_equal(got["images"], frame.images)
    K, _ = python_calibration(FRAME / "calib.json", 1600, 900, reduction=4)
    assert np.array_equal(got["K"], K)


@needs_frame
@pytest.mark.parametrize("which", ["random_model", "trained_model"])
def test_grid_equals_python_onnxruntime(embed_build, which, request, tmp_path):
    model = request.getfixturevalue(which)
    images, K, occupancy, density = python_reference(model, FRAME, FRAME / "calib.json")
    proc, got = cpp_run(embed_build["run"], model, FRAME, FRAME / "calib.json", tmp_path, runs=2)
    assert np.array_equal(got["images"], images)
    assert got["grid"].dtype == np.uint8 and got["grid"].shape == (200, 200, 16)
    assert got["density"].dtype == np.float32 and got["density"].shape == (200, 200, 16)
    assert np.array_equal(got["grid"], occupancy), f"{int((got['grid'] != occupancy).sum())} voxels differ"
    assert float(np.abs(got["density"] - density).max()) <= 1e-6
    counts = np.bincount(occupancy.reshape(-1), minlength=18)
    assert printed_counts(proc.stdout) == {i: int(n) for i, n in enumerate(counts)}
    occupied = 1.0 - counts[17] / occupancy.size
    if which == "random_model":
        assert occupied == 0.0                      # random init: sigma ~ 0.1 < tau everywhere
    else:
        assert 0.005 < occupied < 0.2, occupied     # ~2 % occupied: the comparison covers real labels
        assert (counts[:17] > 0).sum() >= 2
    assert re.search(r"p50 inference: [\d.]+ ms, p50 decode\+inference: [\d.]+ ms \(2 runs\)", proc.stdout)


@needs_frame
def test_resized_png_frame_rescales_intrinsics_like_python(embed_build, trained_model, tmp_path):
    """800x450 PNGs with the 1600x900 calibration: f' = f s, c' = (c + 0.5) s - 0.5, same grid as Python."""
    folder = frame_copy(tmp_path, (800, 450), ".png")
    images, K, occupancy, density = python_reference(trained_model, folder, FRAME / "calib.json")
    calib = json.loads((FRAME / "calib.json").read_text())
    K0 = np.asarray(calib["cameras"]["CAM_FRONT"]["intrinsic"])
    assert abs(K[0, 0, 0] - K0[0, 0] * 0.5) < 1e-3 and abs(K[0, 0, 2] - ((K0[0, 2] + 0.5) * 0.5 - 0.5)) < 1e-3
    _, got = cpp_run(embed_build["run"], trained_model, folder, FRAME / "calib.json", tmp_path / "out")
    assert np.array_equal(got["images"], images)
    np.testing.assert_allclose(got["K"], K, rtol=2e-7, atol=0)
    assert np.array_equal(got["grid"], occupancy), f"{int((got['grid'] != occupancy).sum())} voxels differ"
    assert float(np.abs(got["density"] - density).max()) <= 1e-6


@needs_frame
def test_default_calibration_when_no_calib_given(embed_build, random_model, tmp_path):
    """Without --calib the model's default calibration (480x270 rig) is rescaled to the 1600x900 images."""
    from occflownet.contract import create_session, decode_metadata

    meta = decode_metadata(create_session(random_model).get_modelmeta().custom_metadata_map)
    _, got = cpp_run(embed_build["run"], random_model, FRAME, None, tmp_path)
    calib_file = tmp_path / "default.json"
    calib_file.write_text(json.dumps(meta["default_calibration"]))
    K, _ = python_calibration(calib_file, 1600, 900, reduction=4)
    np.testing.assert_allclose(got["K"], K, rtol=2e-7, atol=0)


# ----------------------------------------------------------------------------------------------- C layer
def test_c_demo_reads_metadata_and_runs(embed_build, random_model):
    proc = run_program(embed_build["c_demo_asan"], random_model)
    assert proc.returncode == 0, proc.stderr
    assert_no_sanitizer_report(proc)
    assert "cameras: CAM_FRONT CAM_FRONT_RIGHT CAM_FRONT_LEFT CAM_BACK CAM_BACK_LEFT CAM_BACK_RIGHT" in proc.stdout
    assert "grid: 200 x 200 x 16, free index 17 (free), default image size 480x270" in proc.stdout
    assert "occupied voxels: 0 of 640000" in proc.stdout
    m = re.search(r"CAM_FRONT intrinsics for 480x270: fx ([\d.]+) fy ([\d.]+) cx ([\d.]+) cy ([\d.]+)", proc.stdout)
    assert m and [float(v) for v in m.groups()] == pytest.approx([379.8, 379.8, 240.0, 135.0], abs=1e-4)
    bad = run_program(embed_build["c_demo_asan"], REPO / "README.md")
    assert bad.returncode == 1 and "onnxruntime cannot load this model" in bad.stderr
    assert_no_sanitizer_report(bad)


@needs_frame
def test_c_layer_calibration_from_json(embed_build, random_model):
    """occflownet_calibration_from_json: the real frame's calibration for 800x450 images, as Python's rule; an
    aspect ratio it cannot match is an error code with the message."""
    proc = run_program(embed_build["c_demo_asan"], random_model, FRAME / "calib.json", 800, 450)
    assert proc.returncode == 0, proc.stderr
    assert_no_sanitizer_report(proc)
    K, _ = python_calibration(FRAME / "calib.json", 800, 450)
    m = re.search(r"CAM_FRONT intrinsics for 800x450: fx ([\d.]+) fy ([\d.]+) cx ([\d.]+) cy ([\d.]+)", proc.stdout)
    assert m, proc.stdout
    assert [float(v) for v in m.groups()] == pytest.approx([K[0, 0, 0], K[0, 1, 1], K[0, 0, 2], K[0, 1, 2]], abs=1e-4)
    bad = run_program(embed_build["c_demo_asan"], random_model, FRAME / "calib.json", 800, 800)
    assert bad.returncode == 1
    assert "CAM_FRONT: image is 800x800 but the calibration is for 1600x900" in bad.stderr
    assert_no_sanitizer_report(bad)


# ----------------------------------------------------------------------------------------------- sanitizer
@needs_frame
def test_asan_run_is_clean_and_equal(embed_build, trained_model, tmp_path):
    """AddressSanitizer + UBSan build (leak check at exit) on the real frame, two runs on the same buffers."""
    proc, got = cpp_run(embed_build["run_asan"], trained_model, FRAME, FRAME / "calib.json", tmp_path / "a", runs=2)
    assert_no_sanitizer_report(proc)
    _, ref = cpp_run(embed_build["run"], trained_model, FRAME, FRAME / "calib.json", tmp_path / "r")
    assert np.array_equal(got["grid"], ref["grid"]) and np.array_equal(got["density"], ref["density"])


# ----------------------------------------------------------------------------------------------- bad inputs
def _break_model(src: Path, dst: Path, how: str) -> Path:
    import onnx

    proto = onnx.load(str(src))
    props = {p.key: p for p in proto.metadata_props}
    if how == "contract-v2":
        props["onnx_contract"].value = json.dumps("v2")
    elif how == "no-cameras":
        keep = [p for p in proto.metadata_props if p.key != "cameras"]
        del proto.metadata_props[:]
        proto.metadata_props.extend(keep)
    elif how == "bad-default-calibration":
        calib = json.loads(props["default_calibration"].value)
        calib["cameras"]["CAM_BACK"]["cam2ego"][0][0] = 2.0
        props["default_calibration"].value = json.dumps(calib)
    elif how == "nested-default-calibration":
        deep = "[" * 2000 + "]" * 2000
        props["default_calibration"].value = props["default_calibration"].value[:-1] + f', "x": {deep}}}'
    elif how == "overflowing-default-calibration":
        calib = json.loads(props["default_calibration"].value)
        calib["cameras"]["CAM_FRONT_LEFT"]["intrinsic"][1][1] = 1e39
        props["default_calibration"].value = json.dumps(calib)
    elif how == "input-renamed":
        old = proto.graph.input[0].name
        proto.graph.input[0].name = "image"
        for node in proto.graph.node:
            node.input[:] = ["image" if n == old else n for n in node.input]
    onnx.save(proto, str(dst))
    return dst


CONTRACT_CASES = {
    "contract-v2": 'onnx_contract is "v2", this library reads "v1"',
    "no-cameras": "model metadata lacks cameras",
    "bad-default-calibration": "default_calibration: CAM_BACK cam2ego rotation is not a proper rotation",
    "input-renamed": "model has no input 'images' (has image, intrinsics, cam2ego)",
    "nested-default-calibration": "default_calibration is nested deeper than 32 levels of arrays and objects",
    "overflowing-default-calibration": "default_calibration: CAM_FRONT_LEFT intrinsic[1][1] must be finite in float32, "
                                       "got 1e+39",
}


@needs_frame
@pytest.mark.parametrize("how", sorted(CONTRACT_CASES))
def test_model_breaking_the_contract_is_refused(embed_build, random_model, tmp_path, how):
    bad = _break_model(random_model, tmp_path / f"{how}.onnx", how)
    proc = run_program(embed_build["run_asan"], "--model", bad, "--images", FRAME, "--out", tmp_path / "g.npy")
    assert proc.returncode == 1, proc.stderr
    assert CONTRACT_CASES[how] in proc.stderr and str(bad) in proc.stderr, proc.stderr
    assert_no_sanitizer_report(proc)
    assert not (tmp_path / "g.npy").exists()


def _case_missing_camera(tmp_path):
    folder = frame_copy(tmp_path)
    (folder / "CAM_BACK.jpg").unlink()
    return folder, FRAME / "calib.json", "missing camera images CAM_BACK.jpg"


def _case_truncated_jpeg(tmp_path):
    folder = frame_copy(tmp_path)
    data = (folder / "CAM_FRONT_LEFT.jpg").read_bytes()
    (folder / "CAM_FRONT_LEFT.jpg").write_bytes(data[: len(data) // 2])
    return folder, FRAME / "calib.json", "CAM_FRONT_LEFT.jpg: corrupt JPEG"


def _case_garbage_jpeg(tmp_path):
    folder = frame_copy(tmp_path)
    data = bytearray((folder / "CAM_BACK.jpg").read_bytes())
    data[4:400] = bytes(396)  # segments after the SOI marker destroyed
    (folder / "CAM_BACK.jpg").write_bytes(bytes(data))
    return folder, FRAME / "calib.json", "CAM_BACK.jpg: not a decodable JPEG image"


def _case_not_an_image(tmp_path):
    folder = frame_copy(tmp_path)
    (folder / "CAM_FRONT.jpg").write_text("hello")
    return folder, FRAME / "calib.json", "CAM_FRONT.jpg: not a JPEG or PNG image"


def _case_aspect_mismatch(tmp_path):
    return (frame_copy(tmp_path, (1000, 1000), ".png"), FRAME / "calib.json",
            "CAM_FRONT: image is 1000x1000 but the calibration is for 1600x900 (aspect ratio 1.000 vs 1.778)")


def _case_mixed_sizes(tmp_path):
    import cv2

    folder = frame_copy(tmp_path)
    im = cv2.imread(str(folder / "CAM_BACK.jpg"))
    (folder / "CAM_BACK.jpg").unlink()
    cv2.imwrite(str(folder / "CAM_BACK.png"), cv2.resize(im, (800, 450)))
    return folder, FRAME / "calib.json", "camera images differ in size"


def _calib_case(tmp_path, mutate, message):
    calib = json.loads((FRAME / "calib.json").read_text())
    mutate(calib)
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(calib))
    return FRAME, path, message


def _case_rotation(tmp_path):
    def mutate(c):
        c["cameras"]["CAM_FRONT_RIGHT"]["cam2ego"][0][1] += 0.1
    return _calib_case(tmp_path, mutate, "CAM_FRONT_RIGHT cam2ego rotation is not a proper rotation")


def _case_calib_lacks_camera(tmp_path):
    return _calib_case(tmp_path, lambda c: c["cameras"].pop("CAM_BACK_LEFT"), "calibration lacks camera CAM_BACK_LEFT")


def _case_intrinsic_shape(tmp_path):
    def mutate(c):
        c["cameras"]["CAM_BACK"]["intrinsic"] = [[1.0, 0.0], [0.0, 1.0]]
    return _calib_case(tmp_path, mutate, "CAM_BACK intrinsic must be a 3x3 array of numbers")


def _case_calib_not_json(tmp_path):
    path = tmp_path / "calib.json"
    path.write_text("{not json")
    return FRAME, path, "calib.json: not valid JSON"


BAD_INPUTS = {name[6:]: fn for name, fn in dict(globals()).items() if name.startswith("_case_")}


@needs_frame
@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_exits_nonzero_naming_the_problem(embed_build, random_model, tmp_path, case):
    folder, calib, message = BAD_INPUTS[case](tmp_path)
    proc = run_program(embed_build["run_asan"], "--model", random_model, "--images", folder, "--calib", calib,
                       "--out", tmp_path / "g.npy")
    assert proc.returncode == 1, (proc.returncode, proc.stderr)
    assert proc.stderr.startswith("occflownet-run: error: ") and message in proc.stderr, proc.stderr
    assert_no_sanitizer_report(proc)
    assert not (tmp_path / "g.npy").exists()


@needs_frame
@pytest.mark.parametrize("name", sorted(FAULTS))
def test_the_calibration_fault_battery_is_refused_as_in_python(embed_build, random_model, tmp_path, name):
    """Each calibration of the fault battery (tests/test_calibration_faults.py: nesting 2,000 deep, 1e308 in an
    intrinsic and a translation, booleans and strings as numbers, bad image sizes, over 1 MiB) is refused by the
    program and by the C layer (occflownet_calibration_from_json) with the message Python gives, nothing written."""
    calib = tmp_path / "calib.json"
    calib.write_text(FAULTS[name][0](json.loads((FRAME / "calib.json").read_text())))
    proc = run_program(embed_build["run_asan"], "--model", random_model, "--images", FRAME, "--calib", calib,
                       "--out", tmp_path / "g.npy")
    assert proc.returncode == 1, (proc.returncode, proc.stderr)
    assert proc.stderr.startswith(f"occflownet-run: error: {calib}") and FAULTS[name][1] in proc.stderr, proc.stderr
    assert_no_sanitizer_report(proc)
    assert not (tmp_path / "g.npy").exists()
    demo = run_program(embed_build["c_demo_asan"], random_model, calib, 1600, 900)
    assert demo.returncode == 1 and FAULTS[name][1] in demo.stderr, demo.stderr
    assert_no_sanitizer_report(demo)


def test_missing_model_and_bad_usage(embed_build, tmp_path):
    proc = run_program(embed_build["run_asan"], "--model", tmp_path / "nope.onnx", "--images", tmp_path,
                       "--out", tmp_path / "g.npy")
    assert proc.returncode == 1 and f"model file not found or unreadable: {tmp_path / 'nope.onnx'}" in proc.stderr
    assert_no_sanitizer_report(proc)
    proc = run_program(embed_build["run"], "--model", "m.onnx", "--images", tmp_path)
    assert proc.returncode == 2 and "--model, --images and --out are required" in proc.stderr
    proc = run_program(embed_build["run"], "--model", "m.onnx", "--images", tmp_path, "--out", "g.npy", "--runs", "0")
    assert proc.returncode == 2 and "--runs needs an integer >= 1" in proc.stderr


def test_unavailable_execution_provider_is_an_error(embed_build, random_model, tmp_path):
    proc = run_program(embed_build["run"], "--model", random_model, "--images", tmp_path, "--out",
                       tmp_path / "g.npy", "--provider", "cuda")
    assert proc.returncode == 1, proc.stderr
    assert "execution provider 'cuda' is not usable" in proc.stderr and "CPUExecutionProvider" in proc.stderr
