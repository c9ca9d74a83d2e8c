"""In-graph image preprocessing: uint8 images of any size → normalised network input, intrinsics adjusted alike.

Policy ("cover, crop bottom-aligned"), identical in training, eager inference and the exported ONNX graph:
1. crop the largest window of the internal aspect ratio H_in : W_in (rounded to whole pixels), horizontally
   centred and vertically bottom-aligned (the sky at the top is dropped, like BEVDet at test time);
2. if that window is at least 4x larger than the internal size, keep every n-th pixel of it,
   n = floor(ratio / 2), so that the resize below sees a 2-4x reduction (speed: casting and filtering the full
   1600x900 frames would dominate the CPU latency of small presets; ``subsample_large_inputs=False`` turns
   this off);
3. resize to exactly (H_in, W_in) with antialiased bilinear interpolation (PIL-like triangle filter,
   ``F.interpolate(..., antialias=True)`` → ONNX ``Resize(mode="linear", antialias=1)``);
4. normalise with the ImageNet mean/std (0..255 scale).

Pixel convention: integer pixel coordinates are pixel centres (OpenCV). The kept pixels are
``u = x_start + n·j``; with ``m`` kept columns and ``s_x = W_in / m`` an input pixel coordinate ``u`` maps to
``u' = ((u - x_start) / n + 0.5) · s_x - 0.5`` on the network input, so ``fx' = fx · s_x / n`` and
``cx' = (cx - x_start) · s_x / n + 0.5 · s_x - 0.5`` (same for y).

The crop window is computed with integer shape arithmetic (``torch.sym_min``/``sym_max``), so one exported graph
accepts any H and W without re-tracing; the intrinsics arithmetic runs in float32 tensors in both torch and ONNX.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def crop_window(height, width, input_size: tuple[int, int], subsample: bool = True):
    """(y_start, x_start, x_end, step): the crop keeps rows ``y_start::step`` (to the bottom of the image) and
    columns ``x_start:x_end:step``. Works on Python ints and on symbolic shape ints (export)."""
    h_in, w_in = input_size
    crop_h = torch.sym_min(height, (2 * width * h_in + w_in) // (2 * w_in))   # round(W * h_in / w_in)
    crop_w = torch.sym_min(width, (2 * height * w_in + h_in) // (2 * h_in))   # round(H * w_in / h_in)
    step = torch.sym_max(1, crop_w // (2 * w_in)) if subsample else 1
    centre = (step - 1) // 2                                                   # keep the middle of each block
    x0 = (width - crop_w) // 2
    return height - crop_h + centre, x0 + centre, x0 + crop_w, step


def adjust_intrinsics(intrinsics: torch.Tensor, y_start, x_start, step, rows, cols,
                      input_size: tuple[int, int]) -> torch.Tensor:
    """Intrinsics [..., 3, 3] of the input image → intrinsics of the network input, for a crop starting at
    (y_start, x_start) keeping every ``step``-th pixel (``rows`` × ``cols`` kept) resized to ``input_size``."""
    zero = torch.zeros((), dtype=torch.float32, device=intrinsics.device)
    # shape ints become float32 tensors first, so eager torch and the ONNX graph do the same float32 arithmetic
    n = zero + step
    sx = input_size[1] / (zero + cols)
    sy = input_size[0] / (zero + rows)
    row0 = intrinsics[..., 0, :] * (sx / n) + intrinsics[..., 2, :] * (sx * (0.5 - (zero + x_start) / n) - 0.5)
    row1 = intrinsics[..., 1, :] * (sy / n) + intrinsics[..., 2, :] * (sy * (0.5 - (zero + y_start) / n) - 0.5)
    return torch.stack([row0, row1, intrinsics[..., 2, :]], dim=-2)


def scale_intrinsics_to_features(intrinsics: torch.Tensor, stride: int) -> torch.Tensor:
    """Network-input intrinsics [..., 3, 3] → feature-map intrinsics (cell j's centre = input pixel 16j + 7.5)."""
    a = 1.0 / stride
    b = 0.5 / stride - 0.5
    row0 = intrinsics[..., 0, :] * a + intrinsics[..., 2, :] * b
    row1 = intrinsics[..., 1, :] * a + intrinsics[..., 2, :] * b
    return torch.stack([row0, row1, intrinsics[..., 2, :]], dim=-2)


def preprocess_images(images: torch.Tensor, intrinsics: torch.Tensor, input_size: tuple[int, int],
                      mean, std, subsample: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 images [B, V, H, W, 3] (RGB) + intrinsics [B, V, 3, 3] for H×W →
    (normalised float32 images [B*V, 3, H_in, W_in], intrinsics [B, V, 3, 3] of the network input)."""
    b, v, height, width, _ = images.shape
    y_start, x_start, x_end, step = crop_window(height, width, input_size, subsample)
    crop = images[:, :, y_start::step, x_start:x_end:step]         # [B, V, rows, cols, 3] uint8
    rows, cols = crop.shape[2], crop.shape[3]
    torch._check(rows > 0)  # tells torch.export the strided crop is non-empty (it always is)
    torch._check(cols > 0)
    x = crop.reshape(b * v, rows, cols, 3).permute(0, 3, 1, 2).to(torch.float32)
    x = F.interpolate(x, size=tuple(input_size), mode="bilinear", align_corners=False, antialias=True)
    mean_t = torch.tensor(mean, dtype=torch.float32, device=images.device).reshape(1, 3, 1, 1)
    inv_std = 1.0 / torch.tensor(std, dtype=torch.float32, device=images.device).reshape(1, 3, 1, 1)
    k = adjust_intrinsics(intrinsics, y_start, x_start, step, rows, cols, input_size)
    return (x - mean_t) * inv_std, k
