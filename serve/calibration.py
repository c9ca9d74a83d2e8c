"""Calibration JSON of a request: parsing, validation, and intrinsics for the images' actual sizes.

Calibration JSON (design notes section 3): ``{"cameras": {"CAM_FRONT": {"intrinsic": 3×3, "cam2ego": 4×4}, ...}}``;
other top-level keys are ignored. ``intrinsic`` is the pinhole matrix in pixels; ``cam2ego`` maps the OpenCV camera
frame (x right, y down, z forward) into the ego frame (x forward, y left, z up), metres.

Which image size the intrinsics are for:
- a camera's own ``"image_size": [w, h]`` if it has one, else the top-level ``"image_size"``;
- without either (a request calibration that gives no size), the intrinsics are taken to be for the image as sent;
- the model's default calibration always carries its ``image_size``.
When an image's size differs from the calibration's size and the aspect ratio agrees within 1 %, the intrinsics
are scaled: ``K' = diag(w/W, h/H, 1) · K`` (fx, cx by the width ratio; fy, cy by the height ratio). When the aspect
ratio differs, the image was cropped or padded in some unknown way, so the request is refused (400) and the client
must send a ``calibration`` part for that image size.
"""
from __future__ import annotations

import json

import numpy as np

ASPECT_TOLERANCE = 0.01
ORTHONORMAL_TOLERANCE = 1e-3


class CalibrationError(ValueError):
    """A request's calibration is unusable; the message names the camera and the field."""


def parse_calibration(data: bytes) -> dict:
    """The ``calibration`` part's bytes → calibration dict (JSON object). Raises CalibrationError."""
    try:
        calib = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise CalibrationError(f"calibration part is not valid UTF-8 JSON: {exc}") from None
    if not isinstance(calib, dict):
        raise CalibrationError("calibration must be a JSON object with a 'cameras' object")
    return calib


def _matrix(value, shape: tuple[int, int], where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where} must be a {shape[0]}x{shape[1]} array of numbers") from None
    if m.shape != shape:
        raise CalibrationError(f"{where} must be {shape[0]}x{shape[1]}, got shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise CalibrationError(f"{where} contains NaN or inf")
    return m


def _image_size(value, where: str) -> tuple[int, int]:
    try:
        w, h = (float(v) for v in value)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where} must be [width, height]") from None
    if not (w >= 1 and h >= 1 and w == int(w) and h == int(h)):
        raise CalibrationError(f"{where} must be two positive integers, got {value}")
    return int(w), int(h)


def validate_calibration(calib: dict, cameras: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, list]:
    """Check ``calib`` for the given cameras (in order).

    Returns (intrinsics float64 [6, 3, 3], cam2ego float64 [6, 4, 4], per-camera (w, h) the intrinsics are for,
    or None where the calibration gives no size). Raises CalibrationError naming the camera and field.
    """
    cams = calib.get("cameras")
    if not isinstance(cams, dict):
        raise CalibrationError("calibration has no 'cameras' object")
    top_size = _image_size(calib["image_size"], "calibration image_size") if "image_size" in calib else None
    Ks, Ts, sizes = [], [], []
    for name in cameras:
        entry = cams.get(name)
        if not isinstance(entry, dict):
            raise CalibrationError(f"calibration lacks camera {name} (has {sorted(cams)})")
        for key in ("intrinsic", "cam2ego"):
            if key not in entry:
                raise CalibrationError(f"calibration of {name} lacks '{key}'")
        K = _matrix(entry["intrinsic"], (3, 3), f"{name} intrinsic")
        if abs(np.linalg.det(K)) < 1e-9:
            raise CalibrationError(f"{name} intrinsic is singular (determinant {np.linalg.det(K):.3g})")
        if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-6):
            raise CalibrationError(f"{name} intrinsic last row must be [0, 0, 1], got {K[2].tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"{name} intrinsic focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        T = _matrix(entry["cam2ego"], (4, 4), f"{name} cam2ego")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
            raise CalibrationError(f"{name} cam2ego last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > ORTHONORMAL_TOLERANCE or np.linalg.det(R) <= 0:
            raise CalibrationError(f"{name} cam2ego rotation is not a proper rotation (orthonormal, det +1)")
        size = _image_size(entry["image_size"], f"{name} image_size") if "image_size" in entry else top_size
        Ks.append(K)
        Ts.append(T)
        sizes.append(size)
    return np.stack(Ks), np.stack(Ts), sizes


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics [..., 3, 3] of an image resized by (sx, sy) in (width, height): K' = diag(sx, sy, 1) · K."""
    return np.diag([sx, sy, 1.0]) @ K


def calibration_for_sizes(calib: dict | None, metadata, sizes: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics float32 [6, 3, 3] for each image's actual (w, h) in ``sizes`` and cam2ego float32 [6, 4, 4].

    ``calib`` None means the model's default calibration (``metadata.default_calibration``). Raises
    CalibrationError when a size cannot be reconciled (aspect ratio differs from the calibration's).
    """
    source = "the model's default calibration" if calib is None else "the request's calibration"
    K, T, calib_sizes = validate_calibration(metadata.default_calibration if calib is None else calib,
                                             metadata.cameras)
    out = []
    for name, k, (w, h), size in zip(metadata.cameras, K, sizes, calib_sizes):
        if size is None or size == (w, h):
            out.append(k)
            continue
        W, H = size
        if abs((w / h) / (W / H) - 1.0) > ASPECT_TOLERANCE:
            raise CalibrationError(
                f"{name}: image is {w}x{h} but {source} is for {W}x{H} (aspect ratio {w / h:.3f} vs {W / H:.3f}); "
                f"send a 'calibration' part with intrinsics for {w}x{h} images")
        out.append(scale_intrinsics(k, w / W, h / H))
    return np.stack(out).astype(np.float32), T.astype(np.float32)
