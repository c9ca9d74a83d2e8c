"""The contract's image rules: decoding, the graph's crop window, and decoding a JPEG at reduced scale. Numpy only.

- **Decoding.** A camera image is JPEG or PNG, decoded to RGB uint8 [H, W, 3] exactly as the sensor stored its
  pixels. EXIF orientation is ignored, because the calibration (intrinsics, cam2ego) describes the stored pixel
  grid; a viewer's rotation would silently break it. One decoder for training data, ``predict``, the server and
  (with libjpeg/libpng, which ignore EXIF too) the C++ runner. OpenCV is imported on first use.
- **Crop window** (:func:`crop_window`): the window the graph keeps of an H × W image (the model's preprocessing
  computes it with the same function on symbolic shapes): the largest window of the internal aspect ratio,
  horizontally centred, bottom-aligned, every ``step``-th pixel when it is ≥ 4x the internal size.
- **Reduced-scale JPEG decoding** (:func:`decode_reduction`): inference paths (``predict``, the server, the C++
  runner) decode a JPEG at 1/n with libjpeg-turbo's DCT scaling instead of decoding every pixel for the graph to
  filter away: n is the largest of 1, 2, 4, 8 whose decoded image still holds a crop window at least as large as
  the network input (the graph then only shrinks it; 1600 x 900 → tiny, 160 x 288: n = 4, 400 x 225; base,
  256 x 704: n = 2, 800 x 450), PNGs are always decoded whole. The decoded image is
  ⌈W/n⌉ x ⌈H/n⌉ and output pixel i averages stored pixels [n·i, n·i + n), so its centre is stored coordinate
  n·i + (n − 1)/2: the intrinsics follow the pixel-centre rule with s = 1/n exactly, ``f' = f/n``,
  ``c' = (c + 0.5)/n − 0.5`` (:func:`occflownet.contract.calibration.Calibration.arrays_for` with
  ``reductions``), whatever the rounding of an odd size. The graph then filters it with the same triangle
  filter. Training decodes whole images (its data loaders are not an inference path); the difference is the one
  between the graph's filter on the whole image (keeping every ``step``-th pixel first where it is ≥ 4x the
  input) and the same filter on an image whose n x n blocks were averaged first: on a trained tiny and the real
  frame, occupancy fed at 1/4 agrees with occupancy fed whole as closely as fed at 1/2 does
  (docs/results.md#inference).
- **Images of different sizes in one frame** (:func:`common_size`, :func:`resize_rgb`): the model takes one
  [6, H, W, 3] tensor, so the inference paths decode each image (at its own 1/n) and resize the ones not at the
  size most of the decoded images have; the intrinsics of a resized image follow by the pixel-centre rule.
"""
from __future__ import annotations

import struct
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
JPEG_REDUCTIONS = (1, 2, 4, 8)    # the scales libjpeg's DCT scaling decodes to, as OpenCV's IMREAD_REDUCED_*
# JPEG start-of-frame markers (baseline, extended, progressive, lossless, arithmetic); not DHT (C4), JPG (C8), DAC (CC).
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_STANDALONE = {0x01, *range(0xD0, 0xD8)}  # TEM, RST0..7: markers without a length field


@dataclass(frozen=True)
class ImageHeader:
    format: str       # "jpeg" or "png"
    width: int
    height: int
    data_start: int   # JPEG: offset of the first scan (SOS); PNG: offset after IHDR


def _jpeg_header(data: bytes) -> ImageHeader:
    pos, size, n = 2, None, len(data)
    while pos < n:
        if data[pos] != 0xFF:
            raise ValueError(f"corrupt JPEG: expected a marker at byte {pos}")
        while pos < n and data[pos] == 0xFF:  # fill bytes
            pos += 1
        if pos >= n:
            break
        marker = data[pos]
        pos += 1
        if marker in _STANDALONE:
            continue
        if marker == 0xD9:
            break
        if pos + 2 > n:
            break
        (length,) = struct.unpack(">H", data[pos:pos + 2])
        if length < 2:
            raise ValueError("corrupt JPEG: segment length < 2")
        if marker in _SOF_MARKERS:
            if pos + 7 > n:
                break
            height, width = struct.unpack(">HH", data[pos + 3:pos + 7])
            size = (width, height)
        if marker == 0xDA:  # start of scan: entropy-coded data follows
            if size is None:
                raise ValueError("corrupt JPEG: scan before any frame header")
            if size[0] == 0 or size[1] == 0:
                raise ValueError("JPEG with zero or deferred (DNL) dimensions is not supported")
            return ImageHeader("jpeg", size[0], size[1], pos)
        pos += length
    raise ValueError("truncated JPEG: no complete frame header and scan")


def _png_header(data: bytes) -> ImageHeader:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ValueError("truncated PNG: no IHDR chunk")
    width, height = struct.unpack(">II", data[16:24])
    if width == 0 or height == 0:
        raise ValueError("PNG with zero width or height")
    return ImageHeader("png", width, height, 33)


def image_header(data: bytes) -> ImageHeader:
    """Format and (width, height) from the header alone (JPEG SOF / PNG IHDR, nothing decoded). Raises ValueError
    for anything but JPEG or PNG."""
    if data[:2] == JPEG_SIGNATURE:
        return _jpeg_header(data)
    if data[:8] == PNG_SIGNATURE:
        return _png_header(data)
    raise ValueError("not a JPEG or PNG image (unrecognised signature)")


def crop_window(height, width, input_size: tuple[int, int], subsample: bool = True, min_=min, max_=max):
    """(y_start, x_start, x_end, step): the graph keeps rows ``y_start::step`` (to the bottom of the image) and
    columns ``x_start:x_end:step`` of an image of ``height`` x ``width`` for a model whose network input is
    ``input_size`` (H_in, W_in). Integer arithmetic only; ``min_``/``max_`` let the model's preprocessing pass
    ``torch.sym_min``/``sym_max`` so that the exported graph computes the same window from the runtime shape."""
    h_in, w_in = input_size
    crop_h = min_(height, (2 * width * h_in + w_in) // (2 * w_in))   # round(W * h_in / w_in)
    crop_w = min_(width, (2 * height * w_in + h_in) // (2 * h_in))   # round(H * w_in / h_in)
    step = max_(1, crop_w // (2 * w_in)) if subsample else 1
    centre = (step - 1) // 2                                          # keep the middle of each block
    x0 = (width - crop_w) // 2
    return height - crop_h + centre, x0 + centre, x0 + crop_w, step


def holding_reductions(width: int, height: int, input_size: tuple[int, int]) -> list[int]:
    """The n of :data:`JPEG_REDUCTIONS` whose decoded image (⌈W/n⌉ x ⌈H/n⌉ of a ``width`` x ``height`` JPEG) still
    holds a crop window (:func:`crop_window`) of at least the network input ``input_size`` (H_in, W_in); 1 always."""
    h_in, w_in = input_size
    out = []
    for n in JPEG_REDUCTIONS:
        w, h = reduced_size(width, height, n)
        y_start, x_start, x_end, _ = crop_window(h, w, (h_in, w_in), subsample=False)
        if n == 1 or (h - y_start >= h_in and x_end - x_start >= w_in):
            out.append(n)
    return out


def decode_reduction(header: ImageHeader, input_size: tuple[int, int] | None) -> int:
    """n for decoding this image at 1/n: the largest of :func:`holding_reductions` — the smallest decoded image
    that still holds the network input ``input_size`` (H_in, W_in), so the graph only shrinks it —; 1 for a PNG or
    when ``input_size`` is None (decode whole)."""
    if header.format != "jpeg" or input_size is None:
        return 1
    return max(holding_reductions(header.width, header.height, tuple(input_size)))


def common_size(sizes: Sequence[tuple[int, int]]) -> tuple[int, int]:
    """The (w, h) of a frame's image tensor when its decoded images (``sizes``, (w, h) in camera order) differ: the
    size most of them have, ties to the earliest camera. The others are resized to it (:func:`resize_rgb`)."""
    counts = Counter(tuple(s) for s in sizes)
    best = max(counts.values())
    return next(tuple(s) for s in sizes if counts[tuple(s)] == best)


def resize_rgb(rgb: np.ndarray, size: tuple[int, int], out: np.ndarray | None = None) -> np.ndarray:
    """A decoded image uint8 [h, w, 3] at ``size`` (w', h') → uint8 [h', w', 3] (into ``out`` when given):
    unchanged when it has that size, else ``cv2.resize`` with INTER_AREA when it has more pixels (shrinking),
    INTER_LINEAR otherwise. Its intrinsics follow by the pixel-centre rule with s = w'/w, h'/h
    (:meth:`occflownet.contract.calibration.Calibration.arrays_for`, ``size``)."""
    import cv2

    w, h = size
    out = np.empty((h, w, 3), np.uint8) if out is None else out
    if out.shape != (h, w, 3):
        raise ValueError(f"out has shape {list(out.shape)}, not {[h, w, 3]}")
    if rgb.shape == out.shape:
        out[...] = rgb
    else:
        shrink = rgb.shape[0] * rgb.shape[1] > h * w
        cv2.resize(rgb, (w, h), dst=out, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return out


def reduced_size(width: int, height: int, reduction: int) -> tuple[int, int]:
    """(w, h) of a ``width`` x ``height`` JPEG decoded at 1/``reduction`` (libjpeg rounds up)."""
    return -(-width // reduction), -(-height // reduction)


def decode_rgb(data: bytes, reduction: int = 1) -> np.ndarray | None:
    """JPEG/PNG bytes → RGB uint8 [H, W, 3] (EXIF orientation ignored), or None if they cannot be decoded.

    ``reduction`` n > 1 decodes a JPEG at 1/n by DCT scaling (OpenCV ``IMREAD_REDUCED_COLOR_n``: ⌈W/n⌉ x ⌈H/n⌉);
    ValueError for a PNG (OpenCV would resize it instead; PNGs are decoded whole, :func:`decode_reduction`)."""
    import cv2

    if reduction not in JPEG_REDUCTIONS:
        raise ValueError(f"reduction must be one of {JPEG_REDUCTIONS}, got {reduction}")
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size == 0:
        return None
    flags = cv2.IMREAD_COLOR
    if reduction > 1:
        if data[:2] != JPEG_SIGNATURE:
            raise ValueError("only JPEGs are decoded at reduced scale")
        flags = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}[reduction]
    bgr = cv2.imdecode(buf, flags | cv2.IMREAD_IGNORE_ORIENTATION)
    # the channel swap in place, by OpenCV's vectorised kernel: numpy's reversed-stride copy took about as long as
    # the decoding itself at 1600x900 (docs/results.md#inference)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=bgr)
