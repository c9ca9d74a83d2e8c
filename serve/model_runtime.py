"""The ONNX model behind the server: an onnxruntime session, its contract-v1 metadata, warm-up and inference.

Everything model-specific the server uses (cameras, classes, grid, colours, default calibration) comes from the
model file's ``metadata_props`` (JSON values, design notes section 7), never from the training code.

Contract v1 (checked at load time):
- inputs  ``images`` uint8 [B, 6, H, W, 3] RGB, ``intrinsics`` float32 [B, 6, 3, 3] (for that H×W),
  ``cam2ego`` float32 [B, 6, 4, 4] (OpenCV camera frame → ego frame);
- outputs ``occupancy`` uint8 [B, X, Y, Z] (classes, ``free_index`` = free), ``density`` float32 [B, X, Y, Z].
"""
from __future__ import annotations

import hashlib
import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from serve.calibration import calibration_for_sizes
from serve.decode import intrinsics_for_size
from serve.settings import ServeSettings

CONTRACT = "v1"
REQUIRED_KEYS = ("classes", "free_index", "grid", "cameras", "class_colors", "threshold", "input_size",
                 "default_calibration", "onnx_contract")
INPUTS = {"images": ("tensor(uint8)", 5), "intrinsics": ("tensor(float)", 4), "cam2ego": ("tensor(float)", 4)}
OUTPUTS = {"occupancy": ("tensor(uint8)", 4), "density": ("tensor(float)", 4)}


class ModelLoadError(RuntimeError):
    """The model file is missing, unreadable, not ONNX, or breaks contract v1; the message names the file."""


@dataclass(frozen=True)
class ModelMetadata:
    """Contract-v1 metadata of one model file (all parsed from JSON ``metadata_props``)."""

    classes: tuple[str, ...]            # class names, index = class id; classes[free_index] is free space
    free_index: int
    grid: dict                          # {"lower", "upper", "voxel_size", "shape", ...}; ego frame, [x, y, z]
    cameras: tuple[str, ...]            # the six camera names in input order
    class_colors: np.ndarray            # uint8 [len(classes), 3] RGB
    threshold: float                    # τ of the σ ≥ τ fusion (informational)
    input_size: tuple[int, int]         # [H, W] the graph resizes to internally (informational)
    default_calibration: dict           # calibration JSON with "image_size": [w, h]
    preset: str | None
    occflownet_version: str | None
    onnx_contract: str
    raw: dict                           # every metadata key, decoded

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.grid["shape"])


def parse_metadata(props: dict[str, str], source: str) -> ModelMetadata:
    """ONNX ``metadata_props`` (str → JSON str) → :class:`ModelMetadata`; ModelLoadError names ``source``."""
    missing = [k for k in REQUIRED_KEYS if k not in props]
    if missing:
        raise ModelLoadError(f"{source}: model metadata lacks {', '.join(missing)} (not an occflownet contract-v1 "
                             "export?)")
    raw = {}
    for key, text in props.items():
        try:
            raw[key] = json.loads(text)
        except (TypeError, ValueError):
            raw[key] = text  # foreign keys may be plain strings; required ones are checked below
    try:
        if raw["onnx_contract"] != CONTRACT:
            raise ValueError(f"onnx_contract is {raw['onnx_contract']!r}, this server speaks {CONTRACT!r}")
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
        if len(cameras) != 6 or len(set(cameras)) != 6:
            raise ValueError(f"cameras must be 6 distinct names, got {list(cameras)}")
        calib = raw["default_calibration"]
        if not isinstance(calib, dict) or len(calib.get("image_size", ())) != 2:
            raise ValueError("default_calibration must be calibration JSON with image_size [w, h]")
        input_size = tuple(int(v) for v in raw["input_size"])
        return ModelMetadata(
            classes=classes, free_index=free, grid=grid, cameras=cameras, class_colors=colors.astype(np.uint8),
            threshold=float(raw["threshold"]), input_size=input_size, default_calibration=calib,
            preset=raw.get("preset"), occflownet_version=raw.get("occflownet_version"),
            onnx_contract=raw["onnx_contract"], raw=raw)
    except (TypeError, ValueError, KeyError) as exc:
        raise ModelLoadError(f"{source}: invalid model metadata: {exc}") from None


def _check_signature(session, source: str) -> None:
    for kind, args, expected in (("input", session.get_inputs(), INPUTS), ("output", session.get_outputs(), OUTPUTS)):
        found = {a.name: a for a in args}
        for name, (dtype, rank) in expected.items():
            if name not in found:
                raise ModelLoadError(f"{source}: model has no {kind} '{name}' (has {sorted(found)})")
            if found[name].type != dtype or len(found[name].shape) != rank:
                raise ModelLoadError(f"{source}: {kind} '{name}' is {found[name].type} rank {len(found[name].shape)}"
                                     f", contract v1 needs {dtype} rank {rank}")


class ModelRuntime:
    """One onnxruntime session plus its metadata. ``infer`` is thread-safe (ORT sessions allow concurrent runs)."""

    def __init__(self, session, metadata: ModelMetadata, path: Path, sha256: str):
        self.session = session
        self.metadata = metadata
        self.path = path
        self.sha256 = sha256
        self.ready = threading.Event()
        self.warmup_error: str | None = None
        self.warmup_seconds: float | None = None
        # (W, H) when the graph fixes the image size (contract v1 allows any; an export may still pin it), else None
        shape = next(a.shape for a in session.get_inputs() if a.name == "images")
        self.fixed_image_size = (shape[3], shape[2]) if all(isinstance(d, int) for d in shape[2:4]) else None

    @classmethod
    def load(cls, path: str | Path, settings: ServeSettings) -> "ModelRuntime":
        """Open ``path`` with onnxruntime and check contract v1. Raises ModelLoadError naming the file."""
        path = Path(path)
        if not str(path):
            raise ModelLoadError("no model given: pass --model FILE or set OCCFLOWNET_MODEL")
        if not path.is_file():
            raise ModelLoadError(f"model file not found: {path}")
        import onnxruntime as ort

        settings = settings.resolved()
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = settings.intra_op_threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if settings.ort_spin else "0")
        try:
            session = ort.InferenceSession(str(path), sess_options=opts, providers=settings.providers)
        except Exception as exc:  # onnxruntime raises several unrelated types for unreadable files
            raise ModelLoadError(f"cannot load model {path}: {type(exc).__name__}: {exc}") from None
        _check_signature(session, str(path))
        metadata = parse_metadata(dict(session.get_modelmeta().custom_metadata_map), str(path))
        digest = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        return cls(session, metadata, path, digest.hexdigest())

    def infer(self, images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray) -> np.ndarray:
        """One frame: images uint8 [6, H, W, 3] RGB, intrinsics float32 [6, 3, 3] for H×W, cam2ego float32
        [6, 4, 4] → occupancy uint8 [X, Y, Z] (ego frame, [x, y, z], ``free_index`` = free)."""
        feeds = {"images": np.ascontiguousarray(images[None], dtype=np.uint8),
                 "intrinsics": np.ascontiguousarray(intrinsics[None], dtype=np.float32),
                 "cam2ego": np.ascontiguousarray(cam2ego[None], dtype=np.float32)}
        (occ,) = self.session.run(["occupancy"], feeds)
        if occ.dtype != np.uint8 or occ.shape != (1, *self.metadata.grid_shape):
            raise RuntimeError(f"model returned occupancy {occ.dtype} {occ.shape}, metadata promises uint8 "
                               f"{(1, *self.metadata.grid_shape)}")
        return occ[0]

    def warm_up(self) -> None:
        """Run one inference on black images of the default calibration's size (or the graph's fixed size); sets
        ``ready`` on success."""
        size = tuple(int(v) for v in self.metadata.default_calibration["image_size"])
        w, h = self.fixed_image_size or size
        t0 = time.perf_counter()
        try:
            K, T = calibration_for_sizes(None, self.metadata, [size] * 6)
            self.infer(np.zeros((6, h, w, 3), np.uint8), intrinsics_for_size(K, [size] * 6, (w, h)), T)
        except Exception as exc:
            self.warmup_error = f"warm-up inference failed: {type(exc).__name__}: {exc}"
            raise
        self.warmup_seconds = time.perf_counter() - t0
        self.ready.set()
