"""The ONNX contract v1 of an exported occupancy model, in one torch-free place (numpy only).

Everything that produces or consumes an exported model — ``export/`` (writes and checks it), ``occflownet predict``
and ``eval --model`` (onnxruntime), ``serve/`` (HTTP), embedders — takes its names, dtypes, metadata keys,
calibration checks and intrinsics rescaling from here. Importing this module imports numpy and
:mod:`occflownet.config` only: no torch, no onnx, no onnxruntime.

Tensors (B = batch, V = 6 cameras in ``CAMERAS`` order, H × W any image size):

==============  =========  ======================  ===========================================================
name            dtype      shape                   meaning
==============  =========  ======================  ===========================================================
``images``      uint8      [B, V, H, W, 3]         RGB, as decoded (the graph crops/resizes inside)
``intrinsics``  float32    [B, V, 3, 3]            pinhole K for *that* H × W, pixels; integer pixel
                                                   coordinates are pixel centres (OpenCV)
``cam2ego``     float32    [B, V, 4, 4]            camera → ego frame: maps OpenCV camera coordinates (x right,
                                                   y down, z forward, metres) to the ego frame of the keyframe
                                                   (x forward, y left, z up, metres); last row [0, 0, 0, 1]
``occupancy``   uint8      [B, 200, 200, 16]       [x, y, z] of the ego-frame grid, classes 0..16, 17 = free
``density``     float32    [B, 200, 200, 16]       σ ∈ [0, 1]
==============  =========  ======================  ===========================================================

Metadata (``metadata_props``, every value JSON-encoded): see :data:`METADATA_KEYS` and :class:`ModelMetadata`.

Calibration JSON (docs/contracts.md): ``{"cameras": {"CAM_FRONT": {"intrinsic": 3×3, "cam2ego": 4×4,
["image_size": [w, h]]}, ...}, ["image_size": [w, h]]}``; other keys are ignored. The intrinsics of a camera are
for its own ``image_size``, else the top-level one, else (no size given) for the images exactly as they come.
:func:`validate_calibration` checks it strictly (shapes, finite values, non-singular K with last row [0, 0, 1]
and positive focal lengths, cam2ego with last row [0, 0, 0, 1] and a proper rotation); every message names the
camera and the field.

Resized images (one rule everywhere, the pixel-centre rule of half-pixel resizing — OpenCV's ``cv2.resize``, the
model's own preprocessing): an image resized by (sx, sy) = (w'/w, h'/h) has ``f' = f·s`` and
``c' = (c + 0.5)·s − 0.5``, i.e. ``K' = A·K`` with ``A = [[sx, 0, (sx − 1)/2], [0, sy, (sy − 1)/2], [0, 0, 1]]``
(:func:`scale_intrinsics`). Only a uniform resize keeps a calibration valid: the aspect ratios must agree within
:data:`ASPECT_TOLERANCE`, else :class:`CalibrationError` (the image was cropped or padded in an unknown way).
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.config import CAMERAS, GRID

CONTRACT_VERSION = "v1"
ASPECT_TOLERANCE = 0.01          # relative difference of w/h allowed when rescaling intrinsics
ORTHONORMAL_TOLERANCE = 1e-3     # max |RᵀR − I| of a cam2ego rotation
SINGULAR_TOLERANCE = 1e-9        # |det K| below this is singular


class ContractError(ValueError):
    """A model file (or the metadata written into one) breaks contract v1; the message names the file and what."""


class CalibrationError(ValueError):
    """A calibration is unusable (or cannot describe the given images); the message names the camera and field."""


class MissingCalibrationField(CalibrationError, KeyError):
    """A camera or field is missing (also a KeyError, for callers that catch lookups)."""

    __str__ = BaseException.__str__       # not KeyError's quoted repr


# ----------------------------------------------------------------------------------------------- tensors
@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output: name, numpy dtype name, shape (None = dynamic dimension)."""

    name: str
    dtype: str
    shape: tuple[int | None, ...]

    @property
    def rank(self) -> int:
        return len(self.shape)

    @property
    def ort_type(self) -> str:
        """The type string onnxruntime reports (``NodeArg.type``)."""
        return {"uint8": "tensor(uint8)", "float32": "tensor(float)"}[self.dtype]

    @property
    def onnx_elem_type(self) -> int:
        """The ``onnx.TensorProto`` element type (UINT8 = 2, FLOAT = 1), without importing onnx."""
        return {"uint8": 2, "float32": 1}[self.dtype]


NUM_CAMERAS = len(CAMERAS)
INPUTS = (TensorSpec("images", "uint8", (None, NUM_CAMERAS, None, None, 3)),
          TensorSpec("intrinsics", "float32", (None, NUM_CAMERAS, 3, 3)),
          TensorSpec("cam2ego", "float32", (None, NUM_CAMERAS, 4, 4)))
OUTPUTS = (TensorSpec("occupancy", "uint8", (None, *GRID.shape)),
           TensorSpec("density", "float32", (None, *GRID.shape)))
INPUT_NAMES = tuple(s.name for s in INPUTS)
OUTPUT_NAMES = tuple(s.name for s in OUTPUTS)


def check_signature(inputs: Sequence[tuple[str, str, Sequence]], outputs: Sequence[tuple[str, str, Sequence]],
                    source: str, exact: bool = False) -> None:
    """Check a graph's inputs/outputs, each given as (name, dtype, shape) with dtype a numpy name ("uint8",
    "float32") or an onnxruntime type string ("tensor(uint8)") and shape entries ints or None/str (dynamic).

    Names, dtypes and ranks must match :data:`INPUTS`/:data:`OUTPUTS` (extra outputs are allowed). ``exact`` also
    requires the same order, nothing extra and the same static dimensions (what ``export`` writes); without it a
    graph may pin a dynamic dimension (e.g. a fixed image size). Raises ContractError naming ``source``.
    """
    for kind, found, specs in (("input", inputs, INPUTS), ("output", outputs, OUTPUTS)):
        by_name = {name: (dtype, list(shape)) for name, dtype, shape in found}
        if exact and [name for name, _, _ in found] != [s.name for s in specs]:
            raise ContractError(f"{source}: graph {kind}s {[n for n, _, _ in found]} differ from contract "
                                f"{CONTRACT_VERSION} {[s.name for s in specs]}")
        for spec in specs:
            if spec.name not in by_name:
                raise ContractError(f"{source}: model has no {kind} '{spec.name}' (has {sorted(by_name)})")
            dtype, shape = by_name[spec.name]
            dims = [d if isinstance(d, int) and not isinstance(d, bool) and d > 0 else None for d in shape]
            ok = dtype in (spec.dtype, spec.ort_type) and len(dims) == spec.rank
            if ok and exact:
                ok = dims == list(spec.shape)
            elif ok:
                ok = all(want is None or got in (None, want) for got, want in zip(dims, spec.shape))
            if not ok:
                raise ContractError(f"{source}: {kind} '{spec.name}' is {dtype} {dims}, contract "
                                    f"{CONTRACT_VERSION} needs {spec.dtype} {list(spec.shape)}")


def session_signature(session) -> tuple[list, list]:
    """(inputs, outputs) of an onnxruntime session as (name, type, shape) triples for :func:`check_signature`."""
    return ([(a.name, a.type, a.shape) for a in session.get_inputs()],
            [(a.name, a.type, a.shape) for a in session.get_outputs()])


def make_feeds(images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray) -> dict[str, np.ndarray]:
    """The contract's input dict from a batch: images uint8 [B, V, H, W, 3], intrinsics [B, V, 3, 3], cam2ego
    [B, V, 4, 4] (cast to the contract's dtypes, C-contiguous). ValueError naming the tensor on a wrong shape."""
    arrays = (images, intrinsics, cam2ego)
    feeds = {}
    for spec, value in zip(INPUTS, arrays):
        a = np.ascontiguousarray(value, dtype=spec.dtype)
        if a.ndim != spec.rank or any(w is not None and g != w for g, w in zip(a.shape, spec.shape)):
            raise ValueError(f"{spec.name}: shape {list(a.shape)} does not fit contract {CONTRACT_VERSION} "
                             f"{list(spec.shape)}")
        feeds[spec.name] = a
    if len({a.shape[0] for a in feeds.values()}) != 1:
        raise ValueError(f"batch sizes differ: {[list(a.shape) for a in feeds.values()]}")
    return feeds


# ----------------------------------------------------------------------------------------------- metadata
# Keys every export writes; REQUIRED_METADATA_KEYS are the ones a consumer cannot do without.
METADATA_KEYS = ("classes", "free_index", "grid", "cameras", "class_colors", "threshold", "input_size", "preset",
                 "default_calibration", "occflownet_version", "onnx_contract")
REQUIRED_METADATA_KEYS = ("classes", "free_index", "grid", "cameras", "class_colors", "threshold", "input_size",
                          "default_calibration", "onnx_contract")


@dataclass(frozen=True)
class ModelMetadata:
    """Contract-v1 metadata of one model file (parsed from its JSON ``metadata_props``)."""

    classes: tuple[str, ...]            # class names, index = class id; classes[free_index] is free space
    free_index: int
    grid: dict                          # {"lower", "upper", "voxel_size", "shape"}; ego frame, axes [x, y, z]
    cameras: tuple[str, ...]            # the camera names in input order (V = 6)
    class_colors: np.ndarray            # uint8 [len(classes), 3] RGB
    threshold: float                    # τ of the fusion σ ≥ τ → class, else free
    input_size: tuple[int, int]         # [H, W] the graph resizes to internally
    default_calibration: dict           # calibration JSON (the training rig) with "image_size": [w, h]
    preset: str | None
    occflownet_version: str | None
    onnx_contract: str
    raw: dict                           # every metadata key, decoded

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.grid["shape"])


def encode_metadata(meta: Mapping[str, object]) -> dict[str, str]:
    """Metadata values → ``metadata_props`` strings (JSON)."""
    return {str(k): json.dumps(v) for k, v in meta.items()}


def decode_metadata(props: Mapping[str, str]) -> dict:
    """``metadata_props`` → values; a value that is not JSON (a foreign key) stays a plain string."""
    out = {}
    for key, text in props.items():
        try:
            out[key] = json.loads(text)
        except (TypeError, ValueError):
            out[key] = text
    return out


def parse_metadata(props: Mapping[str, str], source: str) -> ModelMetadata:
    """``metadata_props`` (str → JSON str) → :class:`ModelMetadata`, checked (contract version, classes and free
    index, colours, grid, six distinct cameras, a valid default calibration with its image size). Raises
    ContractError naming ``source`` and the key."""
    missing = [k for k in REQUIRED_METADATA_KEYS if k not in props]
    if missing:
        raise ContractError(f"{source}: model metadata lacks {', '.join(missing)} (not an occflownet contract-"
                            f"{CONTRACT_VERSION} export?)")
    raw = decode_metadata(props)
    try:
        if raw["onnx_contract"] != CONTRACT_VERSION:
            raise ValueError(f"onnx_contract is {raw['onnx_contract']!r}, this package speaks {CONTRACT_VERSION!r}")
        classes = tuple(str(c) for c in raw["classes"])
        free = int(raw["free_index"])
        if not 0 <= free < len(classes):
            raise ValueError(f"free_index {free} outside the {len(classes)} classes")
        colors = np.asarray(raw["class_colors"], dtype=np.int64)
        if colors.shape != (len(classes), 3) or colors.min() < 0 or colors.max() > 255:
            raise ValueError(f"class_colors must be {len(classes)}x3 values in 0..255, got shape {colors.shape}")
        grid = dict(raw["grid"])
        if len(grid.get("shape", ())) != 3:
            raise ValueError("grid.shape must have 3 entries [X, Y, Z]")
        cameras = tuple(str(c) for c in raw["cameras"])
        if len(cameras) != NUM_CAMERAS or len(set(cameras)) != NUM_CAMERAS:
            raise ValueError(f"cameras must be {NUM_CAMERAS} distinct names, got {list(cameras)}")
        calib = raw["default_calibration"]
        if not isinstance(calib, dict) or "image_size" not in calib:
            raise ValueError("default_calibration must be calibration JSON with image_size [w, h]")
        try:
            validate_calibration(calib, cameras)
        except CalibrationError as exc:
            raise ValueError(f"default_calibration: {exc}") from None
        input_size = tuple(int(v) for v in raw["input_size"])
        if len(input_size) != 2:
            raise ValueError(f"input_size must be [H, W], got {raw['input_size']}")
        return ModelMetadata(
            classes=classes, free_index=free, grid=grid, cameras=cameras, class_colors=colors.astype(np.uint8),
            threshold=float(raw["threshold"]), input_size=input_size, default_calibration=calib,
            preset=raw.get("preset"), occflownet_version=raw.get("occflownet_version"),
            onnx_contract=raw["onnx_contract"], raw=raw)
    except (TypeError, ValueError, KeyError) as exc:
        raise ContractError(f"{source}: invalid model metadata: {exc}") from None


def check_session(session, source: str) -> ModelMetadata:
    """Signature and metadata of an onnxruntime session against contract v1 → its :class:`ModelMetadata`."""
    check_signature(*session_signature(session), source)
    return parse_metadata(dict(session.get_modelmeta().custom_metadata_map), source)


# ----------------------------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class Calibration:
    """A validated calibration for ``cameras`` (in input order).

    intrinsics float64 [V, 3, 3] (pixels, for ``image_sizes[i]``), cam2ego float64 [V, 4, 4] (camera → ego frame),
    image_sizes: per camera the (w, h) the intrinsics are for, or None = for the images as they come."""

    cameras: tuple[str, ...]
    intrinsics: np.ndarray
    cam2ego: np.ndarray
    image_sizes: tuple[tuple[int, int] | None, ...]

    def arrays_for(self, sizes: Sequence[tuple[int, int]], source: str = "the calibration",
                   remedy: str = "a calibration") -> tuple[np.ndarray, np.ndarray]:
        """(intrinsics float32 [V, 3, 3] for each camera's actual image size (w, h) in ``sizes``, cam2ego float32
        [V, 4, 4]): intrinsics rescaled by the pixel-centre rule where a camera's calibrated size differs.
        CalibrationError naming the camera when the aspect ratio differs (``source`` names the calibration,
        ``remedy`` what the user should send instead)."""
        if len(sizes) != len(self.cameras):
            raise ValueError(f"need {len(self.cameras)} image sizes, got {len(sizes)}")
        K = [rescale_intrinsics(k, size, (int(w), int(h)), camera=name, source=source, remedy=remedy)
             for name, k, size, (w, h) in zip(self.cameras, self.intrinsics, self.image_sizes, sizes)]
        return np.stack(K).astype(np.float32), self.cam2ego.astype(np.float32)


def parse_calibration_json(data: bytes | str, source: str = "calibration") -> dict:
    """Calibration JSON text/bytes → dict (a JSON object). CalibrationError naming ``source`` otherwise."""
    try:
        calib = json.loads(data.decode("utf-8") if isinstance(data, bytes) else data)
    except (UnicodeDecodeError, ValueError) as exc:
        raise CalibrationError(f"{source} is not valid UTF-8 JSON: {exc}") from None
    if not isinstance(calib, dict):
        raise CalibrationError(f"{source} must be a JSON object with a 'cameras' object")
    return calib


def load_calibration(path: str | Path, cameras: Sequence[str] = CAMERAS) -> dict:
    """Read and validate a calibration JSON file → the dict. FileNotFoundError, or CalibrationError whose message
    starts with the file name."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"calibration file not found: {path}") from None
    calib = parse_calibration_json(text, str(path))
    try:
        validate_calibration(calib, cameras)
    except CalibrationError as exc:
        raise type(exc)(f"{path}: {exc}") from None
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


def validate_calibration(calib: Mapping, cameras: Sequence[str] = CAMERAS) -> Calibration:
    """Check calibration JSON for ``cameras`` (in order) → :class:`Calibration`.

    Per camera: ``intrinsic`` 3×3 finite, non-singular, last row [0, 0, 1], fx, fy > 0; ``cam2ego`` 4×4 finite,
    last row [0, 0, 0, 1], rotation orthonormal (within 1e-3) with det +1; optional ``image_size`` [w, h]
    (positive integers), else the top-level one. Raises CalibrationError (MissingCalibrationField for a missing
    camera or field) naming the camera and the field."""
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


def calibration_arrays(calib: Mapping, width: int | None = None, height: int | None = None,
                       cameras: Sequence[str] = CAMERAS, source: str = "the calibration"
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Calibration JSON → (intrinsics float32 [V, 3, 3], cam2ego float32 [V, 4, 4]) in ``cameras`` order, for
    images of ``width × height`` (rescaled by the pixel-centre rule where the calibration states another size of the
    same aspect ratio), or as stated when no size is given. Raises CalibrationError (see validate_calibration,
    rescale_intrinsics)."""
    cal = validate_calibration(calib, cameras)
    if width is None or height is None:
        return cal.intrinsics.astype(np.float32), cal.cam2ego.astype(np.float32)
    return cal.arrays_for([(int(width), int(height))] * len(cameras), source)
