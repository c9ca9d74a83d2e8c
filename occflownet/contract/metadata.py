"""Contract v1's model metadata (``metadata_props``, every value JSON-encoded): keys, encoding, strict parsing.

Numpy only.
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from occflownet.contract.calibration import (MAX_CALIBRATION_DEPTH, CalibrationError, json_depth,
                                             parse_calibration_json, validate_calibration)
from occflownet.contract.tensors import CONTRACT_VERSION, NUM_CAMERAS, ContractError

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
    """``metadata_props`` → values; a value that is not JSON (a foreign key), or is nested deeper than
    MAX_CALIBRATION_DEPTH arrays and objects (never decoded), stays a plain string."""
    out = {}
    for key, text in props.items():
        try:
            out[key] = json.loads(text) if json_depth(text) <= MAX_CALIBRATION_DEPTH else text
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
        if isinstance(calib, str):      # not decoded: the calibration rules say why (size, nesting, JSON)
            calib = parse_calibration_json(calib, "default_calibration")
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
