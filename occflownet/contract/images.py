"""The contract's image rule: a camera image is JPEG or PNG, decoded to RGB uint8 [H, W, 3] exactly as the sensor
stored its pixels. EXIF orientation is ignored, because the calibration (intrinsics, cam2ego) describes the stored
pixel grid; a viewer's rotation would silently break it. One decoder for training data, ``predict``, the server
and (with libjpeg/libpng, which ignore EXIF too) the C++ runner. OpenCV is imported on first use.
"""
from __future__ import annotations

import numpy as np


def decode_rgb(data: bytes) -> np.ndarray | None:
    """JPEG/PNG bytes → RGB uint8 [H, W, 3] (EXIF orientation ignored), or None if they cannot be decoded."""
    import cv2

    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size == 0:
        return None
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    return None if bgr is None else np.ascontiguousarray(bgr[:, :, ::-1])
