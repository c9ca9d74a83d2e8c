"""In-graph image preprocessing: uint8 images of any size → normalised network input, intrinsics adjusted alike.

Policy ("cover, crop bottom-aligned"), identical in training, eager inference and the exported ONNX graph:
1. crop the largest window of the internal aspect ratio H_in : W_in (rounded to whole pixels), horizontally
   centred and vertically bottom-aligned (the sky at the top is dropped, like BEVDet at test time);
2. resize that window to exactly (H_in, W_in) with antialiased bilinear interpolation (PIL-like triangle filter,
   ``F.interpolate(..., antialias=True)`` → ONNX ``Resize(mode="linear", antialias=1)``);
3. normalise with the ImageNet mean/std (0..255 scale).

Pixel convention: integer pixel coordinates are pixel centres (OpenCV). An input pixel coordinate ``u`` maps to
the network-input coordinate ``u' = (u + 0.5 - x0) * s_x - 0.5`` with ``s_x = W_in / crop_width`` (same for y),
so ``fx' = s_x fx`` and ``cx' = s_x (cx + 0.5 - x0) - 0.5``.

The crop window is computed with integer shape arithmetic (``torch.sym_min``), so one exported graph accepts any
H and W without re-tracing.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def crop_window(height, width, input_size: tuple[int, int]):
    """(y0, x0, crop_h, crop_w) of the bottom-aligned, horizontally centred crop with the internal aspect ratio.

    Works on Python ints and on symbolic shape ints (export)."""
    h_in, w_in = input_size
    crop_h = torch.sym_min(height, (2 * width * h_in + w_in) // (2 * w_in))   # round(W * h_in / w_in)
    crop_w = torch.sym_min(width, (2 * height * w_in + h_in) // (2 * h_in))   # round(H * w_in / h_in)
    return height - crop_h, (width - crop_w) // 2, crop_h, crop_w


def adjust_intrinsics(intrinsics: torch.Tensor, window, input_size: tuple[int, int]) -> torch.Tensor:
    """Intrinsics [..., 3, 3] of the input image → intrinsics of the cropped + resized network input."""
    y0, x0, crop_h, crop_w = window
    zero = torch.zeros((), dtype=torch.float32, device=intrinsics.device)
    # shape ints become float32 tensors first, so eager torch and the ONNX graph do the same float32 arithmetic
    sx = input_size[1] / (zero + crop_w)
    sy = input_size[0] / (zero + crop_h)
    row0 = intrinsics[..., 0, :] * sx + intrinsics[..., 2, :] * (sx * (0.5 - (zero + x0)) - 0.5)
    row1 = intrinsics[..., 1, :] * sy + intrinsics[..., 2, :] * (sy * (0.5 - (zero + y0)) - 0.5)
    return torch.stack([row0, row1, intrinsics[..., 2, :]], dim=-2)


def scale_intrinsics_to_features(intrinsics: torch.Tensor, stride: int) -> torch.Tensor:
    """Network-input intrinsics [..., 3, 3] → feature-map intrinsics (cell j's centre = input pixel 16j + 7.5)."""
    a = 1.0 / stride
    b = 0.5 / stride - 0.5
    row0 = intrinsics[..., 0, :] * a + intrinsics[..., 2, :] * b
    row1 = intrinsics[..., 1, :] * a + intrinsics[..., 2, :] * b
    return torch.stack([row0, row1, intrinsics[..., 2, :]], dim=-2)


def preprocess_images(images: torch.Tensor, intrinsics: torch.Tensor, input_size: tuple[int, int],
                      mean, std) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 images [B, V, H, W, 3] (RGB) + intrinsics [B, V, 3, 3] for H×W →
    (normalised float32 images [B*V, 3, H_in, W_in], intrinsics [B, V, 3, 3] of the network input)."""
    b, v, height, width, _ = images.shape
    window = crop_window(height, width, input_size)
    y0, x0, crop_h, crop_w = window
    crop = images[:, :, y0:, x0:x0 + crop_w]                                   # [B, V, crop_h, crop_w, 3]
    x = crop.reshape(b * v, crop_h, crop_w, 3).permute(0, 3, 1, 2).to(torch.float32)
    x = F.interpolate(x, size=tuple(input_size), mode="bilinear", align_corners=False, antialias=True)
    mean_t = torch.tensor(mean, dtype=torch.float32, device=images.device).reshape(1, 3, 1, 1)
    inv_std = 1.0 / torch.tensor(std, dtype=torch.float32, device=images.device).reshape(1, 3, 1, 1)
    return (x - mean_t) * inv_std, adjust_intrinsics(intrinsics, window, input_size)
