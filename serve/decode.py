"""Camera images of a request: header sniffing (size before decoding), OpenCV decoding, a common tensor size.

- :func:`image_header` (the contract's, :mod:`occflownet.contract.images`) reads the pixel size from the JPEG SOF /
  PNG IHDR header without decoding, so an image whose header claims more pixels than the limit is refused before
  any pixel buffer is allocated; the same header gives the scale a JPEG is decoded at for the model
  (:func:`decode_reduction`, :func:`decoded_size`: libjpeg-turbo's DCT scaling, as ``predict`` and the C++ runner).
- :func:`decode_image` decodes to RGB uint8 [H, W, 3] as stored (EXIF orientation is ignored: calibrations refer to
  the sensor's pixel grid), refusing truncated files (JPEG without EOI after the scan, PNG without IEND).
- the graph takes one [6, H, W, 3] tensor, so when the six images differ in size each one is resized to the
  :func:`common_size` (the size most cameras share; ties go to the earlier camera in camera order) while it is
  decoded into its slice of the tensor; its intrinsics are computed for that size in the one rescale of
  :func:`occflownet.runtime.frame_calibration` (``serve/calibration.py``). Images that already have the common size
  are decoded straight into place, untouched.
"""
from __future__ import annotations

from collections import Counter

import cv2
import numpy as np

from occflownet.contract import ImageHeader, decode_reduction, decode_rgb, image_header, reduced_size

__all__ = ["ImageError", "ImageHeader", "check_header", "common_size", "decode_image", "decode_reduction",
           "decoded_size", "image_header"]


class ImageError(ValueError):
    """A camera's image part is unusable; ``camera`` names the part, ``status`` is the HTTP status to answer."""

    def __init__(self, camera: str, message: str, status: int = 400):
        super().__init__(f"{camera}: {message}")
        self.camera = camera
        self.status = status


def _complete(data: bytes, header: ImageHeader) -> bool:
    """Whether the file reaches its end marker: JPEG EOI after the first scan (0xFFD9 cannot occur inside
    entropy-coded data), PNG IEND chunk."""
    if header.format == "jpeg":
        return data.rfind(b"\xff\xd9") >= header.data_start
    return data.rfind(b"IEND") >= header.data_start


def check_header(camera: str, data: bytes, max_pixels: int) -> ImageHeader:
    """Header-only checks of one image part (nothing decoded): a JPEG or PNG, complete (end marker present), at
    most ``max_pixels`` pixels. Raises ImageError naming ``camera`` (413 for the pixel limit, else 400)."""
    if not data:
        raise ImageError(camera, "image part is empty")
    try:
        header = image_header(data)
    except ValueError as exc:
        raise ImageError(camera, str(exc)) from None
    pixels = header.width * header.height
    if pixels > max_pixels:
        raise ImageError(camera, f"image is {header.width}x{header.height} = {pixels} pixels, over the limit of "
                                 f"{max_pixels} pixels per image", status=413)
    if not _complete(data, header):
        raise ImageError(camera, f"truncated {header.format.upper()} (no end marker): the upload is incomplete")
    return header


def decoded_size(header: ImageHeader, reduction: int) -> tuple[int, int]:
    """(w, h) of the image of ``header`` decoded at 1/``reduction`` (the header's size when 1)."""
    return reduced_size(header.width, header.height, reduction)


def decode_image(camera: str, data: bytes, max_pixels: int, out: np.ndarray | None = None,
                 reduction: int = 1) -> np.ndarray:
    """One image part → RGB uint8 [H, W, 3] (a JPEG at 1/``reduction``, :func:`decode_reduction`), after
    :func:`check_header`. Raises ImageError naming ``camera``.

    With ``out`` (uint8 [h, w, 3], e.g. one camera's slice of the frame tensor) the RGB pixels are written there,
    resized to (w, h) when the image's size differs (INTER_AREA when shrinking, INTER_LINEAR when enlarging)."""
    header = check_header(camera, data, max_pixels)
    rgb = decode_rgb(data, reduction)             # the contract's rule: EXIF orientation ignored
    if rgb is None:
        raise ImageError(camera, f"{header.format.upper()} could not be decoded (corrupt data)")
    w, h = decoded_size(header, reduction)
    if rgb.shape[:2] != (h, w):
        raise ImageError(camera, f"decoded size {rgb.shape[1]}x{rgb.shape[0]} disagrees with the header's "
                                 f"{header.width}x{header.height} at 1/{reduction}")
    if out is None:
        return rgb
    if rgb.shape == out.shape:
        out[...] = rgb
    else:
        shrink = rgb.shape[0] * rgb.shape[1] > out.shape[0] * out.shape[1]
        method = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        cv2.resize(rgb, (out.shape[1], out.shape[0]), dst=out, interpolation=method)
    return out


def common_size(sizes: list[tuple[int, int]]) -> tuple[int, int]:
    """The (w, h) most images share; ties go to the earliest in camera order."""
    counts = Counter(sizes)
    best = max(counts.values())
    return next(s for s in sizes if counts[s] == best)

