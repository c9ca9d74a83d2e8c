"""occflownet.runtime, the one predictor path: ModelInputs, the one feeds function (images + calibration → inputs,
intrinsics rescaled once), and the ONNX and torch predictors behind one batched interface."""
import subprocess
import sys

import numpy as np
import pytest
from serve_fixtures import build_fake_model, fake_reference, synthetic_images

from occflownet.contract import (INPUT_NAMES, Calibration, CalibrationError, calibration_arrays, rescale_intrinsics,
                                 scale_intrinsics)
from occflownet.rig import default_rig
from occflownet.runtime import (FrameCalibration, ModelInputs, OnnxPredictor, Predictor, TorchPredictor,
                                frame_calibration, frame_inputs)


def test_importing_the_runtime_pulls_in_neither_torch_nor_onnxruntime():
    code = ("import sys, occflownet.runtime, occflownet.predict; "
            "bad = [m for m in ('torch', 'onnx', 'onnxruntime') if m in sys.modules]; assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


# ---------------------------------------------------------------- ModelInputs

def test_model_inputs_cast_check_and_feed():
    inputs = ModelInputs(np.zeros((1, 6, 9, 16, 3)), np.zeros((1, 6, 3, 3), np.float64), np.zeros((1, 6, 4, 4)))
    feeds = inputs.feeds()
    assert list(feeds) == list(INPUT_NAMES)
    assert [v.dtype for v in feeds.values()] == [np.uint8, np.float32, np.float32]
    assert all(v.flags.c_contiguous for v in feeds.values())
    assert len(inputs) == 1 and inputs.image_size == (16, 9)
    with pytest.raises(ValueError, match="cam2ego"):
        ModelInputs(np.zeros((1, 6, 9, 16, 3)), np.zeros((1, 6, 3, 3)), np.zeros((1, 6, 3, 3)))
    with pytest.raises(ValueError, match="images: shape \\[1, 5, 9, 16, 3\\]"):
        ModelInputs(np.zeros((1, 5, 9, 16, 3)), np.zeros((1, 6, 3, 3)), np.zeros((1, 6, 4, 4)))
    with pytest.raises(ValueError, match="batch sizes differ"):
        ModelInputs(np.zeros((2, 6, 9, 16, 3)), np.zeros((1, 6, 3, 3)), np.zeros((1, 6, 4, 4)))


def test_model_inputs_stack_and_split():
    K, T = np.tile(np.eye(3), (6, 1, 1)), np.tile(np.eye(4), (6, 1, 1))
    a = ModelInputs.frame(np.full((6, 4, 8, 3), 1, np.uint8), K, T)
    b = ModelInputs.frame(np.full((6, 4, 8, 3), 2, np.uint8), 2 * K, T)
    both = ModelInputs.stack([a, b])
    assert len(both) == 2 and both.images.shape == (2, 6, 4, 8, 3)
    first, second = both.split()
    np.testing.assert_array_equal(first.images, a.images)
    np.testing.assert_array_equal(second.intrinsics, b.intrinsics)


# ---------------------------------------------------------------- the one feeds function

def test_frame_inputs_for_images_as_stored_are_the_contracts_arrays():
    calib = default_rig(480, 270)
    images = np.zeros((6, 135, 240, 3), np.uint8)
    inputs = frame_inputs(images, calib)
    K, T = calibration_arrays(calib, 240, 135)
    np.testing.assert_array_equal(inputs.intrinsics[0], K)
    np.testing.assert_array_equal(inputs.cam2ego[0], T)
    assert inputs.images.shape == (1, 6, 135, 240, 3)
    with pytest.raises(CalibrationError, match="CAM_FRONT: image is 240x240 but the calibration is for 480x270"):
        frame_inputs(np.zeros((6, 240, 240, 3), np.uint8), calib)


def test_frame_inputs_of_a_datasets_arrays():
    calib = default_rig(160, 90)
    K, T = calibration_arrays(calib)
    inputs = frame_inputs(np.zeros((6, 90, 160, 3), np.uint8), Calibration.from_arrays(K, T))
    np.testing.assert_array_equal(inputs.intrinsics[0], K)
    np.testing.assert_array_equal(inputs.cam2ego[0], T)


def test_frame_calibration_rescales_once_to_the_tensor_size():
    """The HTTP path's case: images sent at different sizes (one JPEG decoded at 1/2), resized to the common size
    by the server; the intrinsics go from the calibration to the tensor in one rescale, within float32 rounding
    of the old two-step chain (calibration → decoded size in float32, then → tensor size)."""
    calib = default_rig(480, 270)
    sizes = [(960, 540)] + [(240, 135)] * 5
    frame = frame_calibration(calib, sizes, reductions=[2] + [1] * 5, size=(240, 135))
    assert isinstance(frame, FrameCalibration) and frame.size == (240, 135) and frame.image_shape == (6, 135, 240, 3)
    K0 = np.array(calib["cameras"]["CAM_FRONT"]["intrinsic"])
    old = scale_intrinsics(scale_intrinsics(rescale_intrinsics(K0, (480, 270), (960, 540)), 0.5, 0.5)
                           .astype(np.float32), 240 / 480, 135 / 270).astype(np.float32)
    np.testing.assert_allclose(frame.intrinsics[0], old, rtol=1e-6)
    np.testing.assert_array_equal(frame.intrinsics[1:], calibration_arrays(calib, 240, 135)[0][1:])
    with pytest.raises(ValueError, match="images decode to different sizes"):
        frame_calibration(calib, sizes)
    with pytest.raises(ValueError, match="do not have the frame's shape"):
        frame.inputs(np.zeros((6, 136, 240, 3), np.uint8))


# ---------------------------------------------------------------- predictors

def test_onnx_predictor_runs_the_session_batched(tmp_path):
    predictor = OnnxPredictor.open(build_fake_model(tmp_path / "fake.onnx"), threads=1)
    assert isinstance(predictor, Predictor) and predictor.input_size == (128, 352)
    calib = default_rig(480, 270)
    frames = [frame_inputs(np.stack(synthetic_images((96, 54), seed=s)), calib) for s in (0, 1)]
    occupancy, density = predictor(ModelInputs.stack(frames))
    assert occupancy.shape == density.shape == (2, 200, 200, 16)
    assert occupancy.dtype == np.uint8 and density.dtype == np.float32
    for b, f in enumerate(frames):
        np.testing.assert_array_equal(occupancy[b], fake_reference(f.images[0], f.intrinsics[0], f.cam2ego[0]))
    (only,) = predictor.predict(frames[1], ("occupancy",))
    np.testing.assert_array_equal(only, occupancy[1:])


def test_onnx_predictor_names_a_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="ONNX model not found: .*missing.onnx"):
        OnnxPredictor.open(tmp_path / "missing.onnx")


def test_torch_predictor_feeds_the_model_and_selects_outputs():
    torch = pytest.importorskip("torch")

    class Model:
        class cfg:
            input_size = (32, 64)

        def eval(self):
            self.evaluated = True
            return self

        def inference(self, images, intrinsics, cam2ego):
            assert images.dtype == torch.uint8 and intrinsics.dtype == cam2ego.dtype == torch.float32
            assert not torch.is_grad_enabled()
            b = images.shape[0]
            density = intrinsics[:, 0, 0, 0].reshape(b, 1, 1, 1).expand(b, 200, 200, 16).contiguous()
            return torch.full((b, 200, 200, 16), 17, dtype=torch.uint8), density

    predictor = TorchPredictor(Model())
    assert predictor.model.evaluated and predictor.input_size == (32, 64)
    calib = default_rig(480, 270)
    inputs = ModelInputs.stack([frame_inputs(np.zeros((6, 27, 48, 3), np.uint8), calib)] * 2)
    occupancy, density = predictor(inputs)
    assert isinstance(occupancy, np.ndarray) and occupancy.shape == (2, 200, 200, 16)
    np.testing.assert_array_equal(density[:, 0, 0, 0], inputs.intrinsics[:, 0, 0, 0])
    (alone,) = predictor.predict(inputs, ("density",))
    np.testing.assert_array_equal(alone, density)
