"""In-graph image preprocessing: uint8 images of any size → normalised network input, intrinsics adjusted alike.

Policy ("cover, crop bottom-aligned"), identical in training, eager inference and the exported ONNX graph:
1. crop the largest window of the internal aspect ratio H_in : W_in (rounded to whole pixels), horizontally
   centred and vertically bottom-aligned (the sky at the top is dropped, like BEVDet at test time);
2. if that window is at least 4x larger than the internal size, keep every n-th pixel of it,
   n = floor(ratio / 2), so that the resize below sees a 2-4x reduction (speed: casting and filtering the full
   1600x900 frames would dominate the CPU latency of small presets; ``subsample_large_inputs=False`` turns
   this off);
3. resize to exactly (H_in, W_in) with antialiased bilinear interpolation: the triangle (PIL "bilinear") filter
   whose support grows with the reduction, written out as an explicit separable filter (:func:`triangle_weights`,
   :func:`antialiased_resize`): per axis, blocks of 16 output pixels are a banded weight matrix times a window of
   input pixels (``Gather`` + batched ``MatMul`` in ONNX, windows and weights computed in the graph from the
   runtime sizes). It computes what ``F.interpolate(..., mode="bilinear", antialias=True)`` computes (same taps, same
   weights up to float32 rounding), but with operators every ONNX runtime implements the same way: ONNX
   ``Resize(antialias=1)`` is silently ignored by OpenVINO (inputs off by up to 70/255 on the real frame) and
   handled differently by other runtimes, so the graph has no ``Resize`` in its preprocessing at all;
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

from occflownet.contract.images import crop_window as contract_crop_window


def crop_window(height, width, input_size: tuple[int, int], subsample: bool = True):
    """(y_start, x_start, x_end, step): the crop keeps rows ``y_start::step`` (to the bottom of the image) and
    columns ``x_start:x_end:step``. The contract's rule (:func:`occflownet.contract.crop_window`, which the
    reduced-scale JPEG decoding of the inference paths also follows) on Python ints or symbolic shape ints."""
    return contract_crop_window(height, width, input_size, subsample, torch.sym_min, torch.sym_max)


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


BLOCK = 16   # output pixels per block of the banded resampling matrix


def triangle_weights(length_in, length_out: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The antialiased bilinear (triangle) resampling of one axis as banded blocks: (rows int64 [nb, win], weights
    float32 [nb, BLOCK, win]) so that output pixel ``b·BLOCK + k`` is ``sum_t weights[b, k, t] · in[rows[b, t]]``
    (outputs past ``length_out`` in the last block are padding), nb = ceil(length_out / BLOCK).

    Pixel-centre convention (``align_corners=False``): output pixel i is centred at input coordinate
    ``c_i = (i + 0.5) · r`` (pixel j covers [j, j + 1)), r = L_in / L_out. The filter is ``max(0, 1 − |d| / a)``
    with ``d = j + 0.5 − c_i`` and support a = max(r, 1) (plain bilinear when enlarging), normalised to sum 1 over
    the pixels inside the image — PIL's and torch's ``antialias=True`` definition. Block b reads the window of
    ``win = ceil((BLOCK − 1)·r + 2a) + 2`` input pixels starting at ``floor(c_{b·BLOCK} − a + 0.5)``: the supports of
    its outputs span D = (BLOCK − 1)·r + 2a, so they touch at most ceil(D) pixels counted from the start, and the
    window holds them with two to spare; pixels of the window outside the support or the image get weight 0 (so a
    window start that rounds one pixel lower in another runtime gives the same sums). ``length_in`` may be a symbolic
    shape int (export): window and weights are computed in the graph from the runtime size.
    """
    blocks = -(-length_out // BLOCK)
    # ceil(((BLOCK − 1)·L_in + 2·max(L_in, L_out)) / L_out) + 2, in integers (L_in may be a symbolic shape int)
    window = ((BLOCK - 1) * length_in + 2 * torch.sym_max(length_in, length_out) + length_out - 1) // length_out + 2
    zero = torch.zeros((), dtype=torch.float32, device=device)
    ratio = (zero + length_in) / length_out
    support = torch.clamp(ratio, min=1.0)
    centre = (torch.arange(blocks * BLOCK, dtype=torch.float32, device=device) + 0.5) * ratio
    centre = centre.reshape(blocks, BLOCK)                                                  # [nb, BLOCK]
    start = torch.floor(centre[:, 0] - support + 0.5)                                       # [nb]
    j = start[:, None] + torch.arange(window, dtype=torch.float32, device=device)[None, :]  # [nb, win]
    inside = ((j >= 0) & (j <= (zero + length_in) - 1)).to(torch.float32)
    w = torch.clamp(1.0 - torch.abs(j[:, None, :] + 0.5 - centre[:, :, None]) / support, min=0.0)
    w = w * inside[:, None, :]                                                              # [nb, BLOCK, win]
    w = w / torch.clamp(torch.sum(w, dim=2, keepdim=True), min=1e-12)   # padding outputs may have no pixel
    rows = torch.clamp(j, min=0.0).to(torch.int64)
    rows = torch.minimum(rows, torch.zeros_like(rows) + (length_in - 1))
    return rows, w


def resample_rows(x: torch.Tensor, length_out: int, start=0, step=1, length_in=None) -> torch.Tensor:
    """Triangle-filter resampling along axis 1 of the rows ``start + step·j`` (j < ``length_in``, default: all rows)
    of ``x`` [N, L, M] (any dtype: only the gathered rows are cast) → float32 [N, length_out, M]: one ``Gather`` of
    the blocks' windows (whole contiguous rows) and one batched ``MatMul`` with the banded weights (see
    :func:`triangle_weights`). ``start``/``step`` fold a crop and a decimation into the gather, so nothing is
    sliced or copied first."""
    n, _, m = x.shape
    if length_in is None:
        length_in = x.shape[1]
    rows, w = triangle_weights(length_in, length_out, x.device)
    blocks = w.shape[0]
    source = rows.reshape(-1) * step + start                                             # rows of x
    windows = torch.index_select(x, 1, source).to(torch.float32).reshape(n, blocks, -1, m)   # [N, nb, win, M]
    out = torch.matmul(w, windows)                                                       # [N, nb, BLOCK, M]
    return out.reshape(n, blocks * BLOCK, m)[:, :length_out]


def antialiased_resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """float images channels-first [N, C, H, W] → [N, C, size[0], size[1]] by the separable triangle filter: rows
    first, then the columns of the transposed (2-D, per channel) result, transposed back; every gather moves whole
    contiguous rows. (The reference form of the filter; :func:`crop_resize_hwc` is the same filter on the uint8
    images as they come.)

    Equals ``F.interpolate(x, size, mode="bilinear", align_corners=False, antialias=True)`` up to float32
    rounding (≤ 2e-3 on 0..255 images, like torch's own distance from a float64 filter; tested)."""
    n, c, height, width = x.shape
    out_h, out_w = size
    x = resample_rows(x.reshape(n * c, height, width), out_h)                   # [N·C, H_out, W]
    x = resample_rows(x.transpose(1, 2), out_w)                                 # [N·C, W_out, H_out]
    return x.transpose(1, 2).reshape(n, c, out_h, out_w)


def crop_resize_hwc(images: torch.Tensor, y_start, x_start, step, rows, cols,
                    size: tuple[int, int]) -> torch.Tensor:
    """uint8 images channels-last [N, H, W, 3] → float32 channels-first [N, 3, size[0], size[1]]: the crop window
    (rows ``y_start + step·i``, i < ``rows``; columns ``x_start + step·j``, j < ``cols``) resized by the separable
    triangle filter, what ``antialiased_resize`` computes on the cropped, decimated, cast and permuted images.

    Data movement kept small: the row pass gathers whole image rows of the uint8 input (the crop and the
    decimation are its gather indices; only the gathered rows are cast to float) and filters all W·3 values of
    each row; the small result [N, H_out, W, 3] is turned once to [N, W, 3·H_out] (one axis moved: a single-axis
    Transpose), the column pass gathers its rows the same way, and the result [N, W_out, 3, H_out] is turned once
    more into [N, 3, H_out, W_out]."""
    n, height, width, _ = images.shape
    out_h, out_w = size
    x = resample_rows(images.reshape(n, height, width * 3), out_h, y_start, step, rows)   # [N, H_out, W·3]
    x = x.reshape(n, out_h, width, 3).permute(0, 2, 3, 1).reshape(n, width, 3 * out_h)   # [N, W, 3·H_out]
    x = resample_rows(x, out_w, x_start, step, cols)                                      # [N, W_out, 3·H_out]
    return x.reshape(n, out_w, 3, out_h).permute(0, 2, 3, 1)                             # [N, 3, H_out, W_out]


def preprocess_images(images: torch.Tensor, intrinsics: torch.Tensor, input_size: tuple[int, int],
                      mean, std, subsample: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 images [B, V, H, W, 3] (RGB) + intrinsics [B, V, 3, 3] for H×W →
    (normalised float32 images [B*V, 3, H_in, W_in], intrinsics [B, V, 3, 3] of the network input)."""
    b, v, height, width, _ = images.shape
    y_start, x_start, x_end, step = crop_window(height, width, input_size, subsample)
    rows = (height - y_start + step - 1) // step                   # kept rows y_start::step (to the bottom)
    cols = (x_end - x_start + step - 1) // step                    # kept columns x_start:x_end:step
    torch._check(rows > 0)  # tells torch.export the crop is non-empty (it always is)
    torch._check(cols > 0)
    x = crop_resize_hwc(images.reshape(b * v, height, width, 3), y_start, x_start, step, rows, cols,
                        tuple(input_size))                         # [B*V, 3, H_in, W_in] float32
    mean_t = torch.tensor(mean, dtype=torch.float32, device=images.device).reshape(1, 3, 1, 1)
    inv_std = 1.0 / torch.tensor(std, dtype=torch.float32, device=images.device).reshape(1, 3, 1, 1)
    k = adjust_intrinsics(intrinsics, y_start, x_start, step, rows, cols, input_size)
    return (x - mean_t) * inv_std, k
