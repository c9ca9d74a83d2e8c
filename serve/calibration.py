"""The calibration of a request: which calibration JSON applies, and how its errors name the HTTP request.

Only that is HTTP-specific. Parsing, strict validation and the pixel-centre rescaling rule (with its 1 % aspect
ratio check) are the contract's, turned into the model's inputs by the one feeds function
(:func:`occflownet.runtime.frame_calibration`, the same for ``predict``, ``eval``, export parity and the server's
warm-up; docs/contracts.md).
"""
from __future__ import annotations

from occflownet.contract import CalibrationError, ModelMetadata, parse_calibration_json
from occflownet.runtime import FrameCalibration, frame_calibration


def request_calibration(part: bytes | None, metadata: ModelMetadata, sizes: list[tuple[int, int]],
                        reductions: list[int] | None = None, size: tuple[int, int] | None = None
                        ) -> FrameCalibration:
    """The frame's calibration for the model, in ``metadata.cameras`` order: intrinsics float32 [6, 3, 3] (pixels)
    for the image tensor of ``size`` (w, h), cam2ego float32 [6, 4, 4] (OpenCV camera frame → ego frame).

    ``sizes``: each image's (w, h) as sent; ``reductions``: the 1/n each is decoded at (the contract's reduced-scale
    JPEG rule); ``size``: the common size the decoded images are resized to (default: their decoded size, the same
    for all). The intrinsics are rescaled once, from the calibration's size to ``size``.

    ``part`` is the ``calibration`` part's bytes (calibration JSON), None for the model's default calibration.
    Raises :class:`~occflownet.contract.CalibrationError` naming the camera and field, or, for an image whose aspect
    ratio differs from its calibration's, asking for a ``calibration`` part for that size. Whatever else reading
    the client's part raises (a RecursionError, a TypeError of a value the checks did not foresee) is the client's
    input too, and raised as a CalibrationError naming the exception: a calibration part never causes a 500."""
    if part is None:
        return frame_calibration(metadata.default_calibration, sizes, reductions=reductions, size=size,
                                 cameras=metadata.cameras, source="the model's default calibration",
                                 remedy="a 'calibration' part")
    try:
        calib = parse_calibration_json(part, "calibration part")
        return frame_calibration(calib, sizes, reductions=reductions, size=size, cameras=metadata.cameras,
                                 source="the request's calibration", remedy="a 'calibration' part")
    except CalibrationError:
        raise
    except Exception as exc:
        raise CalibrationError(f"calibration part cannot be used: {type(exc).__name__}: {exc}"[:500]) from None
