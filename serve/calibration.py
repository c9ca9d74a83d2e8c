"""The calibration of a request: which calibration JSON applies, and how its errors name the HTTP request.

Only that is HTTP-specific. Parsing, strict validation and the pixel-centre rescaling rule (with its 1 % aspect
ratio check) are the contract's (:mod:`occflownet.contract`, the same for ``predict``, ``eval --model`` and export
parity; docs/contracts.md).
"""
from __future__ import annotations

import numpy as np

from occflownet.contract import ModelMetadata, parse_calibration_json, validate_calibration


def request_calibration(part: bytes | None, metadata: ModelMetadata, sizes: list[tuple[int, int]],
                        reductions: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(intrinsics float32 [6, 3, 3], pixels, each for its image's actual (w, h) in ``sizes`` — decoded at
    1/``reductions[i]`` when given (the contract's reduced-scale JPEG rule); cam2ego float32 [6, 4, 4], OpenCV
    camera frame → ego frame), both in ``metadata.cameras`` order.

    ``part`` is the ``calibration`` part's bytes (calibration JSON), None for the model's default calibration.
    Raises :class:`~occflownet.contract.CalibrationError` naming the camera and field, or, for an image whose aspect
    ratio differs from its calibration's, asking for a ``calibration`` part for that size."""
    if part is None:
        calib, source = metadata.default_calibration, "the model's default calibration"
    else:
        calib, source = parse_calibration_json(part, "calibration part"), "the request's calibration"
    cal = validate_calibration(calib, metadata.cameras)
    return cal.arrays_for(sizes, source, remedy="a 'calibration' part", reductions=reductions)
