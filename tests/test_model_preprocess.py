import numpy as np
import pytest
import torch

from occflownet.model.presets import IMAGENET_MEAN, IMAGENET_STD
from occflownet.model.preprocess import crop_window, preprocess_images, scale_intrinsics_to_features
from occflownet.contract import calibration_arrays
from occflownet.rig import default_rig

INPUT = (160, 288)


def test_crop_window_cases():
    # 1600x900 → 288x160: window 1600x889 (bottom-aligned), every 2nd pixel, starting at the block middle
    assert crop_window(900, 1600, INPUT) == (11, 0, 1600, 2)
    assert crop_window(270, 480, INPUT) == (3, 0, 480, 1)            # synthetic default size: no subsampling
    assert crop_window(200, 900, INPUT) == (0, 270, 630, 1)          # wide image: centred horizontal crop
    assert crop_window(900, 1600, INPUT, subsample=False) == (11, 0, 1600, 1)


def _blob_images(height, width, centres, sigma):
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    imgs = []
    for u, v in centres:
        g = 250.0 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2))
        imgs.append(np.repeat(g[:, :, None], 3, axis=2))
    return np.round(np.stack(imgs)).astype(np.uint8)


@pytest.mark.parametrize("height,width", [(270, 480), (900, 1600), (1000, 1000), (200, 900)])
def test_adjusted_intrinsics_follow_the_pixels(height, width):
    """A blob drawn at the projection of a 3D point lands where the adjusted intrinsics project that point."""
    K, _ = calibration_arrays(default_rig(width, height))
    point = np.array([0.6, 0.8, 10.0])                                 # camera frame (x right, y down, z fwd)
    uv = (K @ point)[:, :2] / (K @ point)[:, 2:]
    sigma = 0.006 * width
    images = _blob_images(height, width, uv, sigma)
    x, k_in = preprocess_images(torch.from_numpy(images)[None], torch.from_numpy(K)[None], INPUT,
                                IMAGENET_MEAN, IMAGENET_STD)
    assert x.shape == (6, 3, *INPUT)
    raw = (x[:, 0] * IMAGENET_STD[0] + IMAGENET_MEAN[0]).numpy()          # back to 0..255
    yy, xx = np.mgrid[0:INPUT[0], 0:INPUT[1]]
    k_in = k_in[0].numpy().astype(np.float64)
    for cam in range(6):
        w = np.clip(raw[cam], 0, None)
        expected = (k_in[cam] @ point)[:2] / (k_in[cam] @ point)[2]
        got = np.array([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])
        assert np.abs(got - expected).max() < 0.1, (cam, got, expected)


def test_feature_intrinsics_map_cell_centres():
    K = torch.tensor([[[200.0, 0.0, 150.0], [0.0, 210.0, 80.0], [0.0, 0.0, 1.0]]])
    kf = scale_intrinsics_to_features(K, 16)[0]
    p = torch.tensor([0.3, -0.2, 4.0])
    u_in = (K[0] @ p)[:2] / p[2]
    u_f = (kf @ p)[:2] / p[2]
    assert torch.allclose(u_f, (u_in + 0.5) / 16 - 0.5, atol=1e-5)   # input pixel 16j + 7.5 = feature cell j


def test_wrong_inputs_are_rejected():
    from occflownet.model import create_model, get_preset

    m = create_model(get_preset("tiny"), seed=0)
    K, T = calibration_arrays(default_rig(64, 64))
    K, T = torch.from_numpy(K)[None], torch.from_numpy(T)[None]
    with pytest.raises(ValueError, match="uint8"):
        m(torch.zeros(1, 6, 64, 64, 3), K, T)
    with pytest.raises(ValueError, match="images"):
        m(torch.zeros(1, 5, 64, 64, 3, dtype=torch.uint8), K, T)
    with pytest.raises(ValueError, match="cam2ego"):
        m(torch.zeros(1, 6, 64, 64, 3, dtype=torch.uint8), K, T[:, :, :3])


def _triangle_matrix(n_in: int, n_out: int) -> np.ndarray:
    """float64 [n_out, n_in]: the antialiased bilinear (PIL triangle) resampling matrix, written independently."""
    r = n_in / n_out
    a = max(r, 1.0)
    centre = (np.arange(n_out) + 0.5)[:, None] * r
    m = np.maximum(0.0, 1.0 - np.abs(np.arange(n_in)[None, :] + 0.5 - centre) / a)
    return m / m.sum(axis=1, keepdims=True)


@pytest.mark.parametrize("h,w,out", [(445, 800, (160, 288)), (267, 480, (160, 288)), (889, 1600, (160, 288)),
                                     (100, 100, (160, 288)), (50, 300, (7, 299)), (17, 3, (5, 1))])
def test_antialiased_resize_is_the_triangle_filter(h, w, out):
    """Known answer: a float64 triangle-filter matrix on each axis (reductions of 1.7x-5.6x, enlargement, mixed)."""
    from occflownet.model.preprocess import antialiased_resize

    x = torch.randint(0, 256, (2, h, w, 3), generator=torch.Generator().manual_seed(h + w)).float()
    got = antialiased_resize(x.permute(0, 3, 1, 2), out).double().numpy()        # [N, C, H_out, W_out]
    want = np.einsum("ih,nhwc,jw->ncij", _triangle_matrix(h, out[0]), x.double().numpy(),
                     _triangle_matrix(w, out[1]), optimize=True)
    assert got.shape == (2, 3, *out)
    assert np.abs(got - want).max() < 5e-3                                           # float32 sums of 0..255


def test_antialiased_resize_matches_torch_antialias():
    """The checkpoints trained with F.interpolate(antialias=True) see the same input (float32 rounding apart)."""
    import torch.nn.functional as F

    from occflownet.model.preprocess import antialiased_resize

    x = torch.randint(0, 256, (6, 445, 800, 3), generator=torch.Generator().manual_seed(0)).float()
    old = F.interpolate(x.permute(0, 3, 1, 2), size=INPUT, mode="bilinear", align_corners=False, antialias=True)
    assert (antialiased_resize(x.permute(0, 3, 1, 2), INPUT) - old).abs().max() < 1e-3


def test_preprocessing_exports_without_resize():
    """The exported preprocessing is plain Gather/MatMul/elementwise: no Resize (whose antialias attribute OpenVINO
    ignores), and onnxruntime agrees with torch."""
    import tempfile
    from pathlib import Path

    import onnxruntime as ort

    from occflownet.export.onnx_export import trace_to_onnx

    class Pre(torch.nn.Module):
        def forward(self, images, intrinsics):
            return preprocess_images(images, intrinsics, INPUT, IMAGENET_MEAN, IMAGENET_STD)

    K, _ = calibration_arrays(default_rig(800, 450))
    images = torch.randint(0, 256, (1, 6, 450, 800, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))
    K = torch.from_numpy(K)[None]
    h, w = torch.export.Dim("h", min=32, max=4096), torch.export.Dim("w", min=32, max=4096)
    with tempfile.TemporaryDirectory() as tmp:
        proto = trace_to_onnx(Pre(), (images, K), Path(tmp) / "pre.onnx", ["images", "intrinsics"], ["x", "k"],
                              {"images": {2: h, 3: w}, "intrinsics": None})
    assert "Resize" not in {n.op_type for n in proto.graph.node}
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    for size in ((450, 800), (900, 1600), (270, 480)):
        imgs = torch.randint(0, 256, (1, 6, *size, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(2))
        Ks = torch.from_numpy(calibration_arrays(default_rig(size[1], size[0]))[0])[None]
        x_t, k_t = preprocess_images(imgs, Ks, INPUT, IMAGENET_MEAN, IMAGENET_STD)
        x_o, k_o = session.run(None, {"images": imgs.numpy(), "intrinsics": Ks.numpy()})
        assert np.abs(x_o - x_t.numpy()).max() < 1e-5 and np.allclose(k_o, k_t.numpy(), rtol=1e-6)


@pytest.mark.parametrize("n_out", [1, 5, 16, 17, 160, 288])
def test_resampling_windows_hold_every_tap(n_out):
    """The banded blocks (their windows sized from the ratio) hold every non-zero tap of the triangle filter: put back
    into a dense [n_out, n_in] matrix they equal the independently written one, for reductions and enlargements."""
    from occflownet.model.preprocess import BLOCK, triangle_weights

    for n_in in list(range(1, 80)) + list(range(80, 1700, 37)):
        rows, w = triangle_weights(n_in, n_out)
        want = _triangle_matrix(n_in, n_out)
        dense = np.zeros((rows.shape[0] * BLOCK, n_in))
        for b in range(rows.shape[0]):
            np.add.at(dense[b * BLOCK:(b + 1) * BLOCK], (slice(None), rows[b].numpy()), w[b].double().numpy())
            for k in range(BLOCK):
                if b * BLOCK + k < n_out:
                    taps = np.flatnonzero(want[b * BLOCK + k] > 0)
                    assert np.isin(taps, rows[b].numpy()).all(), (n_in, n_out, b * BLOCK + k)
        assert np.abs(dense[:n_out] - want).max() < 1e-4, (n_in, n_out)            # float32 weights


@pytest.mark.parametrize("height,width", [(900, 1600), (450, 800), (225, 400), (200, 900), (1000, 1000)])
def test_preprocessing_is_the_crop_then_the_triangle_filter(height, width):
    """Known answer: the graph's preprocessing (crop and decimation folded into the gathers of the two passes, on the
    uint8 images as they come) equals cropping and decimating the images first, then the reference filter, then
    normalising."""
    from occflownet.model.preprocess import antialiased_resize

    images = torch.randint(0, 256, (1, 6, height, width, 3), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(height + width))
    K = torch.from_numpy(calibration_arrays(default_rig(width, height))[0])[None]
    got = preprocess_images(images, K, INPUT, IMAGENET_MEAN, IMAGENET_STD)[0]
    y0, x0, x1, n = crop_window(height, width, INPUT)
    crop = images[0, :, y0::n, x0:x1:n].permute(0, 3, 1, 2).float()                  # [6, 3, rows, cols]
    mean, std = torch.tensor(IMAGENET_MEAN)[:, None, None], torch.tensor(IMAGENET_STD)[:, None, None]
    want = (antialiased_resize(crop, INPUT) - mean) / std
    assert got.shape == want.shape == (6, 3, *INPUT)
    assert (got - want).abs().max() < 1e-4                                           # float32, 0..255 / ~58
