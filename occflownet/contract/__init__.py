"""The ONNX contract v1 of an exported occupancy model, in one torch-free package.

Everything that produces or consumes an exported model — ``export/`` (writes and checks it), ``occflownet predict``
and ``eval --model`` (onnxruntime), ``serve/`` (HTTP), embedders — takes its names, dtypes, metadata keys,
calibration checks, intrinsics rescaling and onnxruntime sessions from here. Importing this package imports numpy and
:mod:`occflownet.occ3d` only: no torch, no onnx; onnxruntime only when a session is made.

Modules: :mod:`~occflownet.contract.tensors` (the tensors, signature check),
:mod:`~occflownet.contract.metadata` (metadata keys and parsing), :mod:`~occflownet.contract.calibration`
(calibration JSON and the rescaling rule), :mod:`~occflownet.contract.images` (image decoding, the graph's crop
window, reduced-scale JPEG decoding),
:mod:`~occflownet.contract.session` (the onnxruntime session). Their
public names are re-exported here: ``from occflownet import contract; contract.create_session(...)``.
:mod:`~occflownet.contract.cpp_header` renders the contract as the C++ header of ``embed/``
(``python -m occflownet.contract.cpp_header``); it is not imported here, so that ``-m`` runs it cleanly.

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
The rule is applied in one place, :meth:`Calibration.arrays_for` (calibration size → stored size → 1/n of a JPEG
decoded at reduced scale → the size a decoded image was resized to), which every inference path reaches through
:func:`occflownet.runtime.frame_inputs`.
"""
from __future__ import annotations
from occflownet.contract.calibration import (ASPECT_TOLERANCE, FLOAT32_LIMIT, MAX_CALIBRATION_BYTES,
                                             MAX_CALIBRATION_DEPTH, MAX_IMAGE_SIDE, ORTHONORMAL_TOLERANCE,
                                             SINGULAR_TOLERANCE, Calibration, CalibrationError,
                                             MissingCalibrationField, calibration_arrays, calibration_json,
                                             load_calibration, parse_calibration_json, rescale_intrinsics,
                                             resize_matrix, scale_intrinsics, validate_calibration)
from occflownet.contract.images import (JPEG_REDUCTIONS, ImageHeader, common_size, crop_window, decode_reduction,
                                        decode_rgb, holding_reductions, image_header, reduced_size, resize_rgb)
from occflownet.contract.metadata import (METADATA_KEYS, REQUIRED_METADATA_KEYS, ModelMetadata, decode_metadata,
                                          encode_metadata, parse_metadata)
from occflownet.contract.session import check_session, create_session
from occflownet.contract.tensors import (CONTRACT_VERSION, INPUT_NAMES, INPUTS, NUM_CAMERAS, OUTPUT_NAMES, OUTPUTS,
                                         ContractError, TensorSpec, check_signature, session_signature)

__all__ = [
    "ASPECT_TOLERANCE", "FLOAT32_LIMIT", "MAX_CALIBRATION_BYTES", "MAX_CALIBRATION_DEPTH", "MAX_IMAGE_SIDE",
    "ORTHONORMAL_TOLERANCE", "SINGULAR_TOLERANCE", "Calibration", "CalibrationError",
    "MissingCalibrationField", "calibration_arrays", "calibration_json", "load_calibration", "parse_calibration_json",
    "rescale_intrinsics", "resize_matrix", "scale_intrinsics", "validate_calibration",
    "JPEG_REDUCTIONS", "ImageHeader", "common_size", "crop_window", "decode_reduction", "decode_rgb",
    "holding_reductions", "image_header", "reduced_size", "resize_rgb", "METADATA_KEYS", "REQUIRED_METADATA_KEYS",
    "ModelMetadata", "decode_metadata", "encode_metadata", "parse_metadata", "check_session", "create_session",
    "CONTRACT_VERSION", "INPUT_NAMES", "INPUTS", "NUM_CAMERAS", "OUTPUT_NAMES", "OUTPUTS", "ContractError",
    "TensorSpec", "check_signature", "session_signature",
]
