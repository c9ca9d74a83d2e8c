"""Calibration JSON: strict validation and the one intrinsics-rescaling rule (pixel centres). Numpy only.

Format and rule: :mod:`occflownet.contract` and docs/contracts.md.
"""
from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract.images import reduced_size
from occflownet.occ3d import CAMERAS

ASPECT_TOLERANCE = 0.01          # relative difference of w/h allowed when rescaling intrinsics
ORTHONORMAL_TOLERANCE = 1e-3     # max |RᵀR − I| of a cam2ego rotation
SINGULAR_TOLERANCE = 1e-9        # |det K| below this is singular
MAX_CALIBRATION_BYTES = 1024 * 1024   # the largest calibration JSON read (UTF-8 bytes), on every path
MAX_CALIBRATION_DEPTH = 32       # the deepest nesting of arrays and objects in calibration JSON (the format needs 5)
MAX_IMAGE_SIDE = 65535           # the largest width or height an image_size may state (a JPEG's largest side)
FLOAT32_LIMIT = 2.0 ** 128 - 2.0 ** 103   # a double rounds to a finite float32 iff its magnitude is below this

_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)


class CalibrationError(ValueError):
    """A calibration is unusable (or cannot describe the given images); the message names the camera and field."""


class MissingCalibrationField(CalibrationError, KeyError):
    """A camera or field is missing (also a KeyError, for callers that catch lookups)."""

    __str__ = BaseException.__str__       # not KeyError's quoted repr


@dataclass(frozen=True)
class Calibration:
    """A validated calibration for ``cameras`` (in input order).

    intrinsics float64 [V, 3, 3] (pixels, for ``image_sizes[i]``), cam2ego float64 [V, 4, 4] (camera → ego frame),
    image_sizes: per camera the (w, h) the intrinsics are for, or None = for the images as they come."""

    cameras: tuple[str, ...]
    intrinsics: np.ndarray
    cam2ego: np.ndarray
    image_sizes: tuple[tuple[int, int] | None, ...]

    @classmethod
    def from_arrays(cls, intrinsics: np.ndarray, cam2ego: np.ndarray, cameras: Sequence[str] = CAMERAS
                    ) -> "Calibration":
        """A dataset's own arrays as a calibration: intrinsics [V, 3, 3] for the images as stored, cam2ego
        [V, 4, 4] (camera → ego frame), taken as they are (not validated: training reads them the same way)."""
        return cls(tuple(cameras), np.asarray(intrinsics, dtype=np.float64), np.asarray(cam2ego, dtype=np.float64),
                   (None,) * len(cameras))

    def arrays_for(self, sizes: Sequence[tuple[int, int]], source: str = "the calibration",
                   remedy: str = "a calibration", reductions: Sequence[int] | None = None,
                   size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(intrinsics float32 [V, 3, 3] for the images as a model is fed them, cam2ego float32 [V, 4, 4]): the one
        place the pixel-centre rule is applied. Per camera, in float64 before the one cast to float32:

        1. from its calibrated size to its image's size (w, h) in ``sizes`` (as stored), where they differ;
           CalibrationError naming the camera when the aspect ratio differs (``source`` names the calibration,
           ``remedy`` what the user should send instead);
        2. ``reductions`` (one n per camera): the image was decoded at 1/n
           (:func:`occflownet.contract.images.decode_reduction`), so s = 1/n exactly (``f' = f/n``,
           ``c' = (c + 0.5)/n − 0.5``);
        3. ``size`` (w, h): the decoded image (⌈w/n⌉ × ⌈h/n⌉) was then resized to ``size`` by its user (the
           server's common size), s = size / decoded size; no aspect check, the resize is known exactly.

        CalibrationError naming the camera when a rescaled intrinsic is beyond float32."""
        if len(sizes) != len(self.cameras):
            raise ValueError(f"need {len(self.cameras)} image sizes, got {len(sizes)}")
        reductions = [1] * len(sizes) if reductions is None else list(reductions)
        K = []
        for name, k, calibrated, (w, h), n in zip(self.cameras, self.intrinsics, self.image_sizes, sizes, reductions):
            k = rescale_intrinsics(k, calibrated, (int(w), int(h)), camera=name, source=source, remedy=remedy)
            if n != 1:
                k = scale_intrinsics(k, 1.0 / n, 1.0 / n)
            decoded = reduced_size(int(w), int(h), n)
            if size is not None and tuple(size) != decoded:
                k = scale_intrinsics(k, size[0] / decoded[0], size[1] / decoded[1])
            if not np.abs(k).max() < FLOAT32_LIMIT:
                raise CalibrationError(f"{name} intrinsic rescaled for a {w}x{h} image is not finite in float32")
            K.append(k)
        return np.stack(K).astype(np.float32), self.cam2ego.astype(np.float32)


def json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in JSON ``text`` (brackets inside strings do not count), found
    without parsing or recursion; exact for valid JSON."""
    bare = np.frombuffer(_JSON_STRING.sub("", text).encode("utf-8", "surrogatepass"), np.uint8)
    steps = (bare == ord("[")).astype(np.int64) + (bare == ord("{")) - (bare == ord("]")) - (bare == ord("}"))
    return int(np.cumsum(steps).max(initial=0))


def parse_calibration_json(data: bytes | str, source: str = "calibration") -> dict:
    """Calibration JSON text/bytes → dict (a JSON object), refusing before it is parsed text of more than
    MAX_CALIBRATION_BYTES UTF-8 bytes or nested deeper than MAX_CALIBRATION_DEPTH arrays and objects.
    CalibrationError naming ``source`` otherwise."""
    size = len(data) if isinstance(data, bytes) else len(data.encode("utf-8", "surrogatepass"))
    if size > MAX_CALIBRATION_BYTES:
        raise CalibrationError(f"{source} is {size} bytes, over the limit of {MAX_CALIBRATION_BYTES} bytes")
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
    except UnicodeDecodeError as exc:
        raise CalibrationError(f"{source} is not valid UTF-8 JSON: {exc}") from None
    if json_depth(text) > MAX_CALIBRATION_DEPTH:
        raise CalibrationError(f"{source} is nested deeper than {MAX_CALIBRATION_DEPTH} levels of arrays and objects")
    try:
        calib = json.loads(text)
    except ValueError as exc:
        raise CalibrationError(f"{source} is not valid UTF-8 JSON: {exc}") from None
    if not isinstance(calib, dict):
        raise CalibrationError(f"{source} must be a JSON object with a 'cameras' object")
    return calib


def load_calibration(path: str | Path, cameras: Sequence[str] = CAMERAS) -> dict:
    """Read and validate a calibration JSON file (at most MAX_CALIBRATION_BYTES) → the dict. FileNotFoundError, or
    CalibrationError whose message starts with the file name."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            text = fh.read(MAX_CALIBRATION_BYTES + 1)
            size = max(len(text), os.fstat(fh.fileno()).st_size)
    except FileNotFoundError:
        raise FileNotFoundError(f"calibration file not found: {path}") from None
    if size > MAX_CALIBRATION_BYTES:
        raise CalibrationError(f"{path} is {size} bytes, over the limit of {MAX_CALIBRATION_BYTES} bytes")
    calib = parse_calibration_json(text, str(path))
    try:
        validate_calibration(calib, cameras)
    except CalibrationError as exc:
        raise type(exc)(f"{path}: {exc}") from None
    return calib


def _token(value) -> str:
    """``value`` as it reads in JSON (``true``, ``"1266.4"``, ``1e+308``), shortened; non-finite floats as inf/nan."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _number(value, where: str) -> float:
    """One JSON number → float; CalibrationError naming ``where`` for a boolean, a string or anything not a number,
    and for a number whose float32 is not finite (the model gets float32)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise CalibrationError(f"{where} must be a JSON number, got {_token(value)}")
    try:
        v = float(value)
    except OverflowError:                      # an integer beyond any double
        v = math.inf
    if not abs(v) < FLOAT32_LIMIT:             # also NaN
        raise CalibrationError(f"{where} must be finite in float32, got {_token(value)}")
    return v


def _rows(value) -> list | None:
    """A JSON array (list or tuple; a numpy array as its nested lists), else None."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    return list(value) if isinstance(value, (list, tuple)) else None


def _matrix(value, shape: tuple[int, int], where: str) -> np.ndarray:
    rows = _rows(value)
    if rows is None or len(rows) != shape[0] or any(_rows(r) is None for r in rows):
        raise CalibrationError(f"{where} must be a {shape[0]}x{shape[1]} array of numbers")
    rows = [_rows(r) for r in rows]
    if any(len(r) != shape[1] for r in rows):
        raise CalibrationError(f"{where} must be {shape[0]}x{shape[1]}, got rows of {[len(r) for r in rows]}")
    return np.array([[_number(x, f"{where}[{i}][{j}]") for j, x in enumerate(r)] for i, r in enumerate(rows)])


def _image_size(value, where: str) -> tuple[int, int]:
    pair = _rows(value)
    if pair is None or len(pair) != 2:
        raise CalibrationError(f"{where} must be [width, height]")
    w, h = (_number(v, f"{where}[{i}]") for i, v in enumerate(pair))
    if not all(1 <= v <= MAX_IMAGE_SIDE and v == int(v) for v in (w, h)):
        raise CalibrationError(f"{where} must be two integers from 1 to {MAX_IMAGE_SIDE}, got {_token(pair)}")
    return int(w), int(h)


def validate_calibration(calib: Mapping, cameras: Sequence[str] = CAMERAS) -> Calibration:
    """Check calibration JSON for ``cameras`` (in order) → :class:`Calibration`.

    Every matrix entry and image size value is a number (a JSON number: not a boolean, not a string; in Python an
    int or float, numpy's included) whose float32 is finite (magnitude below FLOAT32_LIMIT). Per camera:
    ``intrinsic`` 3×3, non-singular, last row [0, 0, 1], fx, fy > 0; ``cam2ego`` 4×4, last row [0, 0, 0, 1],
    rotation orthonormal (within 1e-3) with det +1; optional ``image_size`` [w, h] (integers 1..MAX_IMAGE_SIDE),
    else the top-level one. Raises CalibrationError (MissingCalibrationField for a missing camera or field) naming
    the camera and the field, down to the entry (``CAM_FRONT intrinsic[0][0] must be a JSON number, got true``)."""
    if not isinstance(calib, Mapping):
        raise CalibrationError("calibration must be a JSON object with a 'cameras' object")
    cams = calib.get("cameras")
    if not isinstance(cams, Mapping):
        raise MissingCalibrationField("calibration has no 'cameras' object")
    top = _image_size(calib["image_size"], "calibration image_size") if "image_size" in calib else None
    Ks, Ts, sizes = [], [], []
    for name in cameras:
        entry = cams.get(name)
        if not isinstance(entry, Mapping):
            raise MissingCalibrationField(f"calibration lacks camera {name} (has {sorted(cams)})")
        for key in ("intrinsic", "cam2ego"):
            if key not in entry:
                raise MissingCalibrationField(f"calibration of {name} lacks '{key}'")
        K = _matrix(entry["intrinsic"], (3, 3), f"{name} intrinsic")
        det = np.linalg.det(K)
        if abs(det) < SINGULAR_TOLERANCE:
            raise CalibrationError(f"{name} intrinsic is singular (determinant {det:.3g})")
        if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-6):
            raise CalibrationError(f"{name} intrinsic last row must be [0, 0, 1], got {K[2].tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"{name} intrinsic focal lengths must be positive, got fx={K[0, 0]}, "
                                   f"fy={K[1, 1]}")
        T = _matrix(entry["cam2ego"], (4, 4), f"{name} cam2ego")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
            raise CalibrationError(f"{name} cam2ego last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > ORTHONORMAL_TOLERANCE or np.linalg.det(R) <= 0:
            raise CalibrationError(f"{name} cam2ego rotation is not a proper rotation (orthonormal, det +1)")
        Ks.append(K)
        Ts.append(T)
        sizes.append(_image_size(entry["image_size"], f"{name} image_size") if "image_size" in entry else top)
    return Calibration(tuple(cameras), np.stack(Ks), np.stack(Ts), tuple(sizes))


# ----------------------------------------------------------------------------------------------- rescaling
def resize_matrix(sx: float, sy: float) -> np.ndarray:
    """float64 [3, 3] A with K' = A·K for an image resized by (sx, sy): pixel centres map u' = (u + 0.5)·s − 0.5."""
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics [..., 3, 3] of an image resized by (sx, sy) (width, height ratios), pixel-centre rule:
    fx' = fx·sx, skew' = skew·sx, cx' = (cx + 0.5)·sx − 0.5; fy' = fy·sy, cy' = (cy + 0.5)·sy − 0.5 (float64)."""
    return resize_matrix(sx, sy) @ np.asarray(K, dtype=np.float64)


def rescale_intrinsics(K: np.ndarray, from_size: tuple[int, int] | None, to_size: tuple[int, int],
                       camera: str = "camera", source: str = "the calibration", remedy: str = "a calibration"
                       ) -> np.ndarray:
    """K [3, 3] for images of ``from_size`` (w, h) → K for ``to_size`` (float64); unchanged when ``from_size`` is
    None (the intrinsics are for the images as they come) or equal. CalibrationError naming the camera when the
    aspect ratios differ by more than ASPECT_TOLERANCE."""
    K = np.asarray(K, dtype=np.float64)
    if from_size is None or tuple(from_size) == tuple(to_size):
        return K
    (W, H), (w, h) = from_size, to_size
    if abs((w / h) / (W / H) - 1.0) > ASPECT_TOLERANCE:
        raise CalibrationError(
            f"{camera}: image is {w}x{h} but {source} is for {W}x{H} (aspect ratio {w / h:.3f} vs {W / H:.3f}); "
            f"send {remedy} with intrinsics for {w}x{h} images")
    return scale_intrinsics(K, w / W, h / H)


def calibration_json(intrinsics, cam2ego, image_size: Sequence[int] | None = None,
                     cameras: Sequence[str] = CAMERAS) -> dict:
    """The calibration JSON (docs/contracts.md) of intrinsics [V, 3, 3] and cam2ego [V, 4, 4] in ``cameras`` order,
    with the top-level ``image_size`` [w, h] when given: what :func:`calibration_arrays` reads back."""
    calib = {"cameras": {cam: {"intrinsic": np.asarray(K).tolist(), "cam2ego": np.asarray(T).tolist()}
                         for cam, K, T in zip(cameras, intrinsics, cam2ego, strict=True)}}
    if image_size is not None:
        calib["image_size"] = [int(v) for v in image_size]
    return calib


def calibration_arrays(calib: Mapping, width: int | None = None, height: int | None = None,
                       cameras: Sequence[str] = CAMERAS, source: str = "the calibration", reduction: int = 1
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Calibration JSON → (intrinsics float32 [V, 3, 3], cam2ego float32 [V, 4, 4]) in ``cameras`` order, for
    images of ``width × height`` (rescaled by the pixel-centre rule where the calibration states another size of the
    same aspect ratio), or as stated when no size is given; with ``reduction`` n the images of that size were
    decoded at 1/n (see :meth:`Calibration.arrays_for`). Raises CalibrationError (see validate_calibration,
    rescale_intrinsics)."""
    cal = validate_calibration(calib, cameras)
    if width is None or height is None:
        return cal.intrinsics.astype(np.float32), cal.cam2ego.astype(np.float32)
    return cal.arrays_for([(int(width), int(height))] * len(cameras), source,
                          reductions=[reduction] * len(cameras))
