"""Calibration of a request: the ``calibration`` part parsed, validated and matched to the images' actual sizes.

All the rules are the contract's (:mod:`occflownet.contract`, the same for ``predict``, ``eval --model`` and export
parity): calibration JSON (docs/contracts.md), strict validation naming camera and field, and for an image
whose size differs from the size its intrinsics are for (the camera's own ``image_size``, else the top-level one,
else the image as sent; the model's default calibration always has one) the pixel-centre rule
``f' = f·s, c' = (c + 0.5)·s − 0.5`` when the aspect ratio agrees within 1 %. A different aspect ratio means the
image was cropped or padded in some unknown way: the request is refused (400) and the client must send a
``calibration`` part for that image size.
"""
from __future__ import annotations

import numpy as np

from occflownet.contract import CalibrationError, parse_calibration_json, validate_calibration

__all__ = ["CalibrationError", "calibration_for_sizes", "parse_calibration", "validate_calibration"]


def parse_calibration(data: bytes) -> dict:
    """The ``calibration`` part's bytes → calibration dict (a JSON object). Raises CalibrationError."""
    return parse_calibration_json(data, "calibration part")


def calibration_for_sizes(calib: dict | None, metadata, sizes: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics float32 [6, 3, 3] for each image's actual (w, h) in ``sizes`` and cam2ego float32 [6, 4, 4].

    ``calib`` None means the model's default calibration (``metadata.default_calibration``). Raises
    CalibrationError naming the camera (bad field, or an aspect ratio that differs from the calibration's)."""
    source = "the model's default calibration" if calib is None else "the request's calibration"
    cal = validate_calibration(metadata.default_calibration if calib is None else calib, metadata.cameras)
    return cal.arrays_for(sizes, source, remedy="a 'calibration' part")
